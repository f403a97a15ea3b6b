// The device interface of palpsim-haptic: where the tip is, and where the force goes.
// Scripted devices (a built-in press, a CSV of t,x,y,z, a replayed log) ship here; a
// lab's device SDK plugs in behind the same interface (README.md says how).
#pragma once

#include <memory>
#include <string>
#include <vector>

namespace palpsim::haptic {

/// A point or vector in the CT's physical space (mm or N); the client needs no server types.
struct V3 {
  double x = 0, y = 0, z = 0;
};

/// What the client knows of the patient (from the server's OpenReply) for paths that
/// place themselves, such as the built-in press.
struct PatientBox {
  V3 body_min_mm, body_max_mm;  // bounding box of the body
};

/// A haptic device as the 1 kHz loop sees it. Called from the loop's thread only; each
/// call must return within a small part of the period (no I/O, no waiting).
class Device {
 public:
  virtual ~Device() = default;
  /// Reads the tip position (mm) at loop time t_s (seconds since the loop started).
  /// Returns false when the device has nothing more to give (a script ended).
  virtual bool read_tip(double t_s, V3& tip_mm) = 0;
  /// Sends the force (N) to the actuators; scripted devices have none and ignore it.
  virtual void apply_force(const V3& force_n) { (void)force_n; }
  /// A line naming the device for logs.
  virtual std::string describe() const = 0;
};

/// A path given as samples (t_s, tip_mm), linearly interpolated; ends after the last sample.
class ScriptedDevice : public Device {
 public:
  ScriptedDevice(std::vector<double> t_s, std::vector<V3> tip_mm, std::string what);
  bool read_tip(double t_s, V3& tip_mm) override;
  std::string describe() const override { return what_; }
  /// Duration of the path (s).
  double duration_s() const { return t_.empty() ? 0 : t_.back(); }

 private:
  std::vector<double> t_;
  std::vector<V3> p_;
  std::string what_;
  std::size_t cursor_ = 0;  // the segment of the previous call (time only grows)
};

/// How far the scripted press goes from its start along -y (mm) unless press:X,Y,Z,TRAVEL
/// says, and the most a TRAVEL may say (a trunk's depth from the back).
constexpr double kDefaultPressTravelMm = 40;
constexpr double kMaxPressTravelMm = 300;

/// Makes the device named by --device: "press", "press:X,Y,Z" (start point; presses along
/// -y, i.e. from the back (LPS +y is posterior) towards the front), "press:X,Y,Z,TRAVEL"
/// (the same, TRAVEL mm instead of kDefaultPressTravelMm), "csv:FILE" (columns
/// t,x,y,z in s and mm, header optional) or "replay:FILE" (a palpsim-haptic log: columns
/// time_s, tip_x_mm, tip_y_mm, tip_z_mm). Throws std::runtime_error naming the file, line
/// and problem for bad input.
std::unique_ptr<Device> make_device(const std::string& spec, const PatientBox& box);

}  // namespace palpsim::haptic
