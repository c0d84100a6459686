// Seed 001's contact force (eqs. 1-5) and its sliding contact point, against hand computations.
#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include "hand_models/contact_point/contact_point_law.hpp"

namespace hapticd::hand::contact_point {
namespace {

constexpr double kGamma = 400, kMuStatic = 0.8, kMuDynamic = 0.6;

// A hand point 2 mm into a floor (C at the origin, n up), dx along the surface: eq. 1 gives
// gamma (C - p) = gamma (-dx, 0, 2 mm); the normal part (eq. 2) is 0.8 N up, the tangential (eq. 3)
// -gamma dx along x.
TEST(ContactPointLaw, TheForceIsTheSpringInsideTheConeAndTheKineticForceOutsideIt) {
  const Eigen::Vector3d C(0, 0, 0), n(0, 0, 1);
  const double depth = 0.002, fn = kGamma * depth;
  for (const double dx : {0.0, 0.0005, 0.0015, 0.00159, 0.00161, 0.003, 0.02}) {
    const ContactForce f = contact_force(kGamma, kMuStatic, kMuDynamic, C, n, {dx, 0, -depth});
    EXPECT_NEAR(f.f_n.z(), fn, 1e-12) << dx;
    EXPECT_NEAR(f.f_n.head<2>().norm(), 0, 1e-12) << dx;
    if (kGamma * dx <= kMuStatic * fn) {  // eq. 4: inside
      EXPECT_EQ(f.state, ContactState::stuck) << dx;
      EXPECT_NEAR(f.f_T.x(), -kGamma * dx, 1e-12) << dx;
    } else {  // eq. 5 outside: Coulomb's kinetic force, against the hand's tangential travel
      EXPECT_EQ(f.state, ContactState::sliding) << dx;
      EXPECT_NEAR(f.f_T.x(), -kMuDynamic * fn, 1e-12) << dx;
    }
    EXPECT_NEAR(f.f_T.y(), 0, 1e-12);
    EXPECT_NEAR(f.f_T.z(), 0, 1e-12);
  }
}

// The switch sits exactly at |f_t| = mu_st (f . n): swept in steps of 0.1 % of that offset (half a
// step off it), the last stuck and the first sliding offsets bracket mu_st times the depth.
TEST(ContactPointLaw, TheStateSwitchesWhereTheTangentialForcePassesMuStaticTimesTheNormal) {
  const Eigen::Vector3d C(0.01, -0.02, 0.03), n = Eigen::Vector3d(1, 2, 2).normalized();
  const Eigen::Vector3d t = n.unitOrthogonal();
  const double depth = 0.003, edge = kMuStatic * depth;
  double last_stuck = -1, first_sliding = -1;
  for (int k = 0; k <= 2000; ++k) {
    const double s = (k + 0.5) * 0.001 * edge;
    const ContactForce f = contact_force(kGamma, kMuStatic, kMuDynamic, C, n, C - depth * n + s * t);
    if (f.state == ContactState::stuck) last_stuck = s;
    if (f.state == ContactState::sliding && first_sliding < 0) first_sliding = s;
  }
  EXPECT_LE(last_stuck, edge);
  EXPECT_GT(first_sliding, edge);
  EXPECT_NEAR(first_sliding / edge, 1.0, 0.0011);
  EXPECT_LT(last_stuck, first_sliding);
}

// A hand point outside the object (or on its surface) exerts nothing, whatever its offset; so does
// a non-finite one.
TEST(ContactPointLaw, AHandPointOutsideTheObjectExertsNothing) {
  const Eigen::Vector3d C(0, 0, 0), n(0, 0, 1);
  for (const Eigen::Vector3d& p : {Eigen::Vector3d(0, 0, 0.001), Eigen::Vector3d(0.01, 0, 0),
                                   Eigen::Vector3d(0.05, 0.05, 1e-9), Eigen::Vector3d(NAN, 0, -0.001)}) {
    const ContactForce f = contact_force(kGamma, kMuStatic, kMuDynamic, C, n, p);
    EXPECT_EQ(f.state, ContactState::separated);
    EXPECT_EQ(f.total(), Eigen::Vector3d::Zero());
  }
}

// A sliding point moves along the tangent plane toward the hand point's foot until its tangential
// spring is the kinetic force: from there, the same hand point is stuck on the cone's kinetic edge.
TEST(ContactPointLaw, ASlidingPointStopsWhereItsSpringIsTheKineticForce) {
  const Eigen::Vector3d C(0, 0, 0), n(0, 0, 1), p(0.01, 0.004, -0.002);
  const Eigen::Vector3d C1 = slide_target(kMuDynamic, C, n, p);
  EXPECT_NEAR(C1.z(), 0, 1e-15) << "along the tangent plane";
  const Eigen::Vector2d travel = (p - C).head<2>().normalized();
  EXPECT_NEAR((Eigen::Vector2d(C1.head<2>().normalized()) - travel).norm(), 0, 1e-12) << "toward the hand point";
  const ContactForce f = contact_force(kGamma, kMuStatic, kMuDynamic, C1, n, p);
  EXPECT_EQ(f.state, ContactState::stuck);
  EXPECT_NEAR(f.f_T.norm(), kMuDynamic * f.f_n.norm(), 1e-12);
  // A stuck or separated point stays.
  EXPECT_EQ(slide_target(kMuDynamic, C, n, {0.0001, 0, -0.002}), C);
  EXPECT_EQ(slide_target(kMuDynamic, C, n, {0.05, 0, 0.001}), C);
}

}  // namespace
}  // namespace hapticd::hand::contact_point
