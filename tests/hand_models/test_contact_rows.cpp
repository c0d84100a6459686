// contact_rows' budget: when the hand's contacts, its bodies' supports and its reserves outnumber the
// rows the haptic tick carries, the supports keep up to a third of them and the reserves two, the
// hand's contacts take the rest, a kind that has fewer leaves its rows to the others, and each kind
// keeps its deepest. Every row is told apart by its depth, recovered from its bias.
#include <gtest/gtest.h>

#include <vector>

#include "hand_models/contact_solve.hpp"
#include "hand_test_util.hpp"

namespace hapticd::hand {
namespace {

// Depth ranges that tell the kinds apart, m.
constexpr double kContact0 = 1e-4, kSupport0 = 3e-4, kReserve0 = 5e-4, kStep = 1e-6;

struct Kept {
  std::vector<double> contacts, supports, reserves;  // depths, in the order of the rows
};

class ContactRowsBudget : public ::testing::Test {
 protected:
  // `contacts` hand contacts on the body, `supports` supports under it and `reserves` reserve contacts,
  // each kind with distinct depths in an order that is not the depths' (i * 7 mod count).
  Kept rows_for(int contacts, int supports, int reserves, int max_contacts) {
    s.contacts.clear();
    s.reserve_contacts.clear();
    s.supports.clear();
    ContactBody body;
    body.mass_kg = 0.2;
    body.inertia_W = 1e-4 * Eigen::Matrix3d::Identity();
    body.p_com_W = Eigen::Vector3d(0, 0, -0.02);
    s.bodies = {body};
    const auto point = [&](int i, double depth) {
      PointContact pc;
      const auto [tet, local] = model.node_tet(i % model.num_nodes());
      pc.tet = tet;
      pc.bary = Eigen::Vector4d::Unit(local);
      pc.n_W = Eigen::Vector3d::UnitZ();
      pc.depth_m = depth;
      pc.body = 0;
      pc.constraint = true;
      return pc;
    };
    const auto shuffled = [](int i, int count) { return (7 * i) % count; };  // 7 is prime to the counts
    for (int i = 0; i < contacts; ++i) s.contacts.push_back(point(i, kContact0 + kStep * shuffled(i, contacts)));
    for (int i = 0; i < reserves; ++i)
      s.reserve_contacts.push_back(point(i, kReserve0 + kStep * shuffled(i, reserves)));
    for (int i = 0; i < supports; ++i) {
      BodySupport b;
      b.body = 0;
      b.p_W = Eigen::Vector3d(0.001 * i, 0, -0.03);
      b.depth_m = kSupport0 + kStep * shuffled(i, supports);
      s.supports.push_back(b);
    }
    assemble(model, s);
    EXPECT_EQ(static_cast<int>(s.active_contacts.size()), contacts);
    ContactRows rows;
    contact_rows(model, s, max_contacts, rows);
    const double h = model.config().dt_s;
    Kept kept;
    for (int k = 0; k < rows.count(); ++k) {
      const double depth = rows.bias[k] * h / kContactDepthRecovery;
      (depth < kSupport0 - 1e-9   ? kept.contacts
       : depth < kReserve0 - 1e-9 ? kept.supports
                                  : kept.reserves)
          .push_back(depth);
    }
    return kept;
  }
  // The `n` deepest of a kind of `count` rows starting at depth0, deepest first.
  static std::vector<double> deepest(int n, int count, double depth0) {
    std::vector<double> d;
    for (int i = 0; i < n; ++i) d.push_back(depth0 + kStep * (count - 1 - i));
    return d;
  }
  static void expect_depths(const std::vector<double>& got, const std::vector<double>& want, const char* kind) {
    ASSERT_EQ(got.size(), want.size()) << kind;
    for (size_t i = 0; i < got.size(); ++i) EXPECT_NEAR(got[i], want[i], 1e-12) << kind << " row " << i;
  }
  HandConfig config;
  HandModel model = testing_util::slab_hand(1, config);
  HandState s = make_rest_state(model);
};

TEST_F(ContactRowsBudget, SupportsKeepAThirdReservesTwoAndTheHandTheRestEachItsDeepest) {
  const Kept k = rows_for(40, 12, 30, 24);
  expect_depths(k.contacts, deepest(14, 40, kContact0), "contacts");
  expect_depths(k.supports, deepest(8, 12, kSupport0), "supports");
  expect_depths(k.reserves, deepest(2, 30, kReserve0), "reserves");
}

TEST_F(ContactRowsBudget, RowsAKindLeavesGoToTheOthersInOrder) {
  // Three supports leave five of their eight rows to the hand's contacts.
  Kept k = rows_for(40, 3, 30, 24);
  expect_depths(k.contacts, deepest(19, 40, kContact0), "contacts");
  expect_depths(k.supports, deepest(3, 3, kSupport0), "supports");
  expect_depths(k.reserves, deepest(2, 30, kReserve0), "reserves");
  // Five hand contacts leave their rows to the supports first, then to the reserves.
  k = rows_for(5, 16, 30, 24);
  expect_depths(k.contacts, deepest(5, 5, kContact0), "contacts");
  expect_depths(k.supports, deepest(16, 16, kSupport0), "supports");
  expect_depths(k.reserves, deepest(3, 30, kReserve0), "reserves");
  // Under the budget every row stays.
  k = rows_for(10, 4, 6, 24);
  EXPECT_EQ(k.contacts.size(), 10u);
  EXPECT_EQ(k.supports.size(), 4u);
  EXPECT_EQ(k.reserves.size(), 6u);
}

}  // namespace
}  // namespace hapticd::hand
