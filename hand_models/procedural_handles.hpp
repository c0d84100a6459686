#pragma once
// The handles of the procedural hand (procedural_hand.hpp): which nodes each handle of a stylus or a
// glove hand takes, the tracked frame each follows, the handle of each skin vertex, the soft joint
// flesh of a glove hand, and the handle targets of a posture.
#include <vector>

#include "hand_models/hand_model.hpp"
#include "hand_models/procedural_hand.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"

namespace hapticd::hand {

// Handle seeds for m tracked frames on a procedural hand: 1 = palm (a stylus),
// 6 = palm + five distal phalanges, 16 = palm + 15 phalanges, otherwise palm +
// the first m - 1 phalanges in finger-major order. Throws for m outside [1, 16].
// On a separate_fingers hand each handle takes only its own part's nodes (the
// palm's or its finger's), none shared with another handle.
std::vector<HandleSpec> procedural_handles(const ProceduralHand& hand, int m);
// The tracked frame each of those handles follows, at rest in the hand frame:
// the palm's (the hand frame itself) for handle 0, the phalanx segment frames
// (hand_skeleton.hpp) for the others.
std::vector<HandFrame> procedural_handle_frames(const ProceduralHand& hand, int m);
// Per skin vertex, the handle whose part of the hand it is on (for the contact
// flags of a glove's frames): the phalanx of the nearest bone (a point behind
// a finger's base joint is palm), that finger's handle when only its distal
// phalanx has one (m = 6), else the palm's handle 0.
std::vector<int> procedural_skin_handles(const ProceduralHand& hand, int m);
// Per tet of a 16-handle glove hand (HandConfig::element_stiffness): `scale`
// for joint flesh, 1 elsewhere. Joint flesh: a tet with a node within
// +-kJointBand flesh radii of a joint (along the bisector of its bones), or
// with nodes on two bones (a finger's bones, or the palm at its base joint).
// Per-bone flesh joined by soft joints: bending a finger costs little elastic
// work, so a glove frame feels the flesh little beyond what it touches. Empty
// for other handle sets and for a hand without separate fingers.
inline constexpr double kJointBand = 0.6;
// The joint flesh's Young's modulus over the hand's, for gloves.
inline constexpr double kGloveJointStiffness = 0.05;
std::vector<double> procedural_joint_stiffness(const ProceduralHand& hand, int m, double scale);
// The handle targets of a hand in posture `angles` with its hand frame (palm
// centre) at (p_W, q_W): each handle's tracked frame posed by the skeleton
// (hand_skeleton.hpp), then carried to the handle by frame_to_handle. What a
// glove in that posture asks of the hand; at rest_joint_angles() the handles'
// rest poses. `left`: the hand is a left one (its skeleton mirrored).
std::vector<HandleTarget> posture_targets(const ProceduralHand& hand, const HandModel& model,
                                          const HandJointAngles& angles, const Eigen::Vector3d& p_W,
                                          const Eigen::Quaterniond& q_W, bool left);

}  // namespace hapticd::hand
