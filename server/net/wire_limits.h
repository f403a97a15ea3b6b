// The limits of the pose and control paths and of local force model patches
// (PROTOCOL.md): sizes the sockets and the parsers refuse beyond, and the patch geometry.
#pragma once

#include <cstddef>
#include <cstdint>

namespace palpsim::net {

/// Limits of the two paths (PROTOCOL.md).
constexpr std::size_t kMaxPoseBytes = 1024;
constexpr std::size_t kMaxControlBytes = 1 << 20;
/// Local force model patches (PoseRequest.local_model_edge, local_model_period_s): voxels
/// per axis and the period between patches (s). 16^3 voxels are 68 KiB on the wire.
constexpr int kMinPatchEdge = 4, kMaxPatchEdge = 16;
constexpr double kMinPatchPeriodS = 0.01, kMaxPatchPeriodS = 1.0;
/// A patch is sent early when the tip comes within this many voxels of the last box's faces.
constexpr double kPatchMarginVox = 2.0;
/// A patch's box is centred ahead of the tip by its velocity (since the last patch) times this
/// (s), at most so far that the tip stays kPatchMarginVox + 1 voxels inside: a patch is used
/// a round trip after it was cut, longer when TCP waits for a lost segment (100 to 300 ms
/// at 100 ms round trip and 1 % loss), and a box centred on the tip where it was cut covers
/// 10 mm ahead at most (12 voxels of 2 mm), 0.5 s at 20 mm/s.
constexpr double kPatchLeadS = 0.25;
/// The largest PoseReply: a small reply and the largest patch (C 1, F 4, grad F 12 bytes a voxel).
constexpr std::size_t kMaxPoseReplyBytes = 4096 + std::size_t(kMaxPatchEdge) * kMaxPatchEdge * kMaxPatchEdge * 17;
/// Longest ControlRequest.client_token (bytes).
constexpr std::size_t kMaxClientTokenBytes = 64;
/// ZeroMQ drops connections that send frames larger than this (memory guard).
constexpr std::int64_t kMaxFrameBytes = 16 << 20;

}  // namespace palpsim::net
