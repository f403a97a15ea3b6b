// A headless OpenGL 4.5 core context through EGL, with no X server and no window:
// EGL_EXT_platform_device (the NVIDIA driver on the GPU machine, Mesa's software device
// here), or EGL_MESA_platform_surfaceless as a fallback. One code path for both.
#pragma once

#include <memory>
#include <string>

namespace palpsim::render {

/// An OpenGL 4.5 core context that renders into framebuffer objects only. It is current
/// on the thread that created it; every GL object of the renderer lives in it, so one
/// thread owns the context and all rendering (the server's render thread).
class EglContext {
 public:
  /// Opens the first EGL device that gives OpenGL 4.5 core, preferring hardware
  /// devices to software ones ($PALPSIM_EGL_DEVICE=N picks device N), then Mesa's
  /// surfaceless platform; makes the context current on the calling thread. Throws
  /// palpsim::Error saying what was tried and why each attempt failed.
  static std::unique_ptr<EglContext> create();
  ~EglContext();
  EglContext(const EglContext&) = delete;
  EglContext& operator=(const EglContext&) = delete;

  /// Makes the context current on the calling thread (after another thread released it).
  void make_current();
  /// Releases it from the calling thread.
  void release_current();

  /// GL_RENDERER, GL_VERSION and GL_VENDOR as the driver reports them.
  const std::string& renderer() const { return renderer_; }
  const std::string& version() const { return version_; }
  const std::string& vendor() const { return vendor_; }
  /// How the display was opened: "device N" or "surfaceless".
  const std::string& platform() const { return platform_; }
  /// True for a software rasteriser (llvmpipe, softpipe, swrast).
  bool software() const { return software_; }
  /// True when the GL device is an NVIDIA GPU (CUDA-GL interop and nvJPEG may be used).
  bool nvidia() const { return nvidia_; }
  /// "renderer (version) via platform", for the server's log.
  std::string describe() const;

 private:
  EglContext() = default;
  void* display_ = nullptr;  // EGLDisplay
  void* context_ = nullptr;  // EGLContext
  std::string renderer_, version_, vendor_, platform_;
  bool software_ = false, nvidia_ = false;
};

}  // namespace palpsim::render
