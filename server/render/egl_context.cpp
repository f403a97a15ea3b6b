#include "render/egl_context.h"

#include <EGL/egl.h>
#include <EGL/eglext.h>
#define GL_GLEXT_PROTOTYPES
#include <GL/glcorearb.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <mutex>
#include <string>
#include <vector>

#include "core/error.h"

namespace palpsim::render {
namespace {

// EGL's error code in hex, as the EGL headers name them ("0x3001")
std::string egl_error() {
  char b[16];
  std::snprintf(b, sizeof b, "0x%04X", unsigned(eglGetError()));
  return std::string("EGL error ") + b;
}

bool has_extension(const char* list, const char* name) {
  if (!list) return false;
  const std::size_t n = std::strlen(name);
  for (const char* p = list; (p = std::strstr(p, name)) != nullptr; p += n)
    if ((p == list || p[-1] == ' ') && (p[n] == ' ' || p[n] == '\0')) return true;
  return false;
}

// eglInitialize and eglTerminate are not reference counted (a device's display is one
// handle per process), so contexts sharing a display count here and the last one out
// terminates it
std::mutex g_display_mu;
std::map<EGLDisplay, int> g_display_users;

void display_acquired(EGLDisplay d) {
  std::lock_guard<std::mutex> lock(g_display_mu);
  ++g_display_users[d];
}

void display_released(EGLDisplay d) {
  std::lock_guard<std::mutex> lock(g_display_mu);
  auto it = g_display_users.find(d);
  if (it == g_display_users.end() || --it->second > 0) return;
  g_display_users.erase(it);
  eglTerminate(d);
}

// the EGL extension entry points (not exported as prototypes by every libEGL)
struct EglExt {
  PFNEGLQUERYDEVICESEXTPROC query_devices = nullptr;
  PFNEGLQUERYDEVICESTRINGEXTPROC query_device_string = nullptr;
  PFNEGLGETPLATFORMDISPLAYEXTPROC get_platform_display = nullptr;
};

EglExt load_ext() {
  EglExt e;
  e.query_devices = reinterpret_cast<PFNEGLQUERYDEVICESEXTPROC>(eglGetProcAddress("eglQueryDevicesEXT"));
  e.query_device_string =
      reinterpret_cast<PFNEGLQUERYDEVICESTRINGEXTPROC>(eglGetProcAddress("eglQueryDeviceStringEXT"));
  e.get_platform_display =
      reinterpret_cast<PFNEGLGETPLATFORMDISPLAYEXTPROC>(eglGetProcAddress("eglGetPlatformDisplayEXT"));
  return e;
}

// a display with an OpenGL 4.5 core context current on it, or why not
struct Opened {
  EGLDisplay display = EGL_NO_DISPLAY;
  EGLContext context = EGL_NO_CONTEXT;
  std::string error;
};

// Initialises `d`, makes a surfaceless OpenGL 4.5 core context and makes it current;
// on failure undoes what it did and says which call failed.
Opened open_on(EGLDisplay d) {
  Opened o;
  if (d == EGL_NO_DISPLAY) {
    o.error = "no display (" + egl_error() + ")";
    return o;
  }
  EGLint major = 0, minor = 0;
  if (!eglInitialize(d, &major, &minor)) {
    o.error = "eglInitialize failed (" + egl_error() + ")";
    return o;
  }
  display_acquired(d);
  auto fail = [&](const std::string& what) {
    o.error = what;
    display_released(d);
    return o;
  };
  const char* ext = eglQueryString(d, EGL_EXTENSIONS);
  if (!has_extension(ext, "EGL_KHR_surfaceless_context"))
    return fail("EGL " + std::to_string(major) + "." + std::to_string(minor) +
                " display lacks EGL_KHR_surfaceless_context");
  if (!eglBindAPI(EGL_OPENGL_API)) return fail("eglBindAPI(EGL_OPENGL_API) failed (" + egl_error() + ")");
  // a config only where the display needs one (EGL_KHR_no_config_context otherwise)
  EGLConfig config = EGL_NO_CONFIG_KHR;
  if (!has_extension(ext, "EGL_KHR_no_config_context")) {
    const EGLint want[] = {EGL_RENDERABLE_TYPE, EGL_OPENGL_BIT, EGL_SURFACE_TYPE, EGL_PBUFFER_BIT, EGL_NONE};
    const EGLint any[] = {EGL_RENDERABLE_TYPE, EGL_OPENGL_BIT, EGL_NONE};
    EGLint n = 0;
    if ((!eglChooseConfig(d, want, &config, 1, &n) || n < 1) && (!eglChooseConfig(d, any, &config, 1, &n) || n < 1))
      return fail("no EGL config renders OpenGL (" + egl_error() + ")");
  }
  const EGLint attrs[] = {EGL_CONTEXT_MAJOR_VERSION,
                          4,
                          EGL_CONTEXT_MINOR_VERSION,
                          5,
                          EGL_CONTEXT_OPENGL_PROFILE_MASK,
                          EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT,
                          EGL_NONE};
  EGLContext c = eglCreateContext(d, config, EGL_NO_CONTEXT, attrs);
  if (c == EGL_NO_CONTEXT) return fail("eglCreateContext(OpenGL 4.5 core) failed (" + egl_error() + ")");
  if (!eglMakeCurrent(d, EGL_NO_SURFACE, EGL_NO_SURFACE, c)) {
    const std::string e = egl_error();
    eglDestroyContext(d, c);
    return fail("eglMakeCurrent(surfaceless) failed (" + e + ")");
  }
  // the driver may give a higher version; refuse a lower one
  GLint gl_major = 0, gl_minor = 0, profile = 0;
  glGetIntegerv(GL_MAJOR_VERSION, &gl_major);
  glGetIntegerv(GL_MINOR_VERSION, &gl_minor);
  glGetIntegerv(GL_CONTEXT_PROFILE_MASK, &profile);
  if (gl_major * 10 + gl_minor < 45 || !(profile & GL_CONTEXT_CORE_PROFILE_BIT)) {
    eglMakeCurrent(d, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
    eglDestroyContext(d, c);
    return fail("the context is OpenGL " + std::to_string(gl_major) + "." + std::to_string(gl_minor) +
                ((profile & GL_CONTEXT_CORE_PROFILE_BIT) ? " core" : " (not core)") + ", not 4.5 core");
  }
  o.display = d;
  o.context = c;
  return o;
}

// what a device calls itself, for the error message ("EGL_MESA_device_software", "/dev/dri/card0")
std::string device_label(const EglExt& e, EGLDeviceEXT dev, bool software) {
  std::string label = software ? "software" : "hardware";
  if (e.query_device_string) {
    const char* drm = e.query_device_string(dev, EGL_DRM_DEVICE_FILE_EXT);
    if (drm) label += std::string(", ") + drm;
  }
  return label;
}

}  // namespace

std::unique_ptr<EglContext> EglContext::create() {
  const EglExt e = load_ext();
  const char* client_ext = eglQueryString(EGL_NO_DISPLAY, EGL_EXTENSIONS);
  std::vector<std::string> tried;
  Opened got;
  std::string platform;

  // 1. EGL devices (EGL_EXT_platform_device): hardware first, or the one $PALPSIM_EGL_DEVICE names
  const char* pick = std::getenv("PALPSIM_EGL_DEVICE");
  const bool picked = pick && *pick;
  if (e.query_devices && e.get_platform_display && has_extension(client_ext, "EGL_EXT_platform_device")) {
    EGLint n = 0;
    std::vector<EGLDeviceEXT> devices;
    if (e.query_devices(0, nullptr, &n) && n > 0) {
      devices.resize(std::size_t(n));
      if (!e.query_devices(n, devices.data(), &n)) n = 0;
      devices.resize(std::size_t(n));
    }
    if (devices.empty()) tried.push_back("eglQueryDevicesEXT found no device (" + egl_error() + ")");
    std::vector<bool> software(devices.size(), false);
    for (std::size_t i = 0; i < devices.size(); ++i) {
      const char* dext = e.query_device_string ? e.query_device_string(devices[i], EGL_EXTENSIONS) : nullptr;
      software[i] = has_extension(dext, "EGL_MESA_device_software");
    }
    std::vector<int> order;
    if (picked) {
      char* end = nullptr;
      const long want = std::strtol(pick, &end, 10);
      if (*end != '\0' || want < 0 || want >= long(devices.size()))
        throw Error("PALPSIM_EGL_DEVICE = '" + std::string(pick) + "' does not name one of the " +
                    std::to_string(devices.size()) + " EGL devices (0.." + std::to_string(int(devices.size()) - 1) +
                    ")");
      order.push_back(int(want));
    } else {
      for (int pass = 0; pass < 2; ++pass)
        for (std::size_t i = 0; i < devices.size(); ++i)
          if (software[i] == (pass == 1)) order.push_back(int(i));
    }
    for (int i : order) {
      Opened o = open_on(e.get_platform_display(EGL_PLATFORM_DEVICE_EXT, devices[std::size_t(i)], nullptr));
      const std::string name = "device " + std::to_string(i);
      if (o.context != EGL_NO_CONTEXT) {
        got = o;
        platform = name;
        break;
      }
      tried.push_back(name + " (" + device_label(e, devices[std::size_t(i)], software[i]) + "): " + o.error);
    }
    if (picked && got.context == EGL_NO_CONTEXT)
      throw Error("no OpenGL 4.5 core context on the EGL device PALPSIM_EGL_DEVICE = " + std::string(pick) + ": " +
                  tried.back());
  } else {
    if (picked)
      throw Error("PALPSIM_EGL_DEVICE = '" + std::string(pick) +
                  "' names an EGL device, but this EGL has no EGL_EXT_platform_device");
    tried.push_back("EGL_EXT_platform_device is not available");
  }

  // 2. Mesa's surfaceless platform
  if (got.context == EGL_NO_CONTEXT) {
    if (e.get_platform_display && has_extension(client_ext, "EGL_MESA_platform_surfaceless")) {
      Opened o = open_on(e.get_platform_display(EGL_PLATFORM_SURFACELESS_MESA, EGL_DEFAULT_DISPLAY, nullptr));
      if (o.context != EGL_NO_CONTEXT) {
        got = o;
        platform = "surfaceless";
      } else {
        tried.push_back("surfaceless: " + o.error);
      }
    } else {
      tried.push_back("surfaceless: EGL_MESA_platform_surfaceless is not available");
    }
  }
  if (got.context == EGL_NO_CONTEXT) {
    std::string msg = "no OpenGL 4.5 core context through EGL: ";
    for (std::size_t i = 0; i < tried.size(); ++i) msg += (i ? "; " : "") + tried[i];
    throw Error(msg);
  }

  // what the driver says it is
  std::unique_ptr<EglContext> c(new EglContext());
  c->display_ = got.display;
  c->context_ = got.context;
  c->platform_ = platform;
  auto str = [](GLenum name) {
    const GLubyte* s = glGetString(name);
    return s ? std::string(reinterpret_cast<const char*>(s)) : std::string();
  };
  c->renderer_ = str(GL_RENDERER);
  c->version_ = str(GL_VERSION);
  c->vendor_ = str(GL_VENDOR);
  c->software_ = c->renderer_.find("llvmpipe") != std::string::npos ||
                 c->renderer_.find("softpipe") != std::string::npos ||
                 c->renderer_.find("swrast") != std::string::npos;
  c->nvidia_ = c->vendor_.find("NVIDIA") != std::string::npos;
  return c;
}

EglContext::~EglContext() {
  const EGLDisplay d = static_cast<EGLDisplay>(display_);
  if (d == EGL_NO_DISPLAY) return;
  if (eglGetCurrentContext() == static_cast<EGLContext>(context_))
    eglMakeCurrent(d, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
  eglDestroyContext(d, static_cast<EGLContext>(context_));
  display_released(d);
}

void EglContext::make_current() {
  if (!eglMakeCurrent(static_cast<EGLDisplay>(display_), EGL_NO_SURFACE, EGL_NO_SURFACE,
                      static_cast<EGLContext>(context_)))
    throw Error("eglMakeCurrent failed (" + egl_error() + ")");
}

void EglContext::release_current() {
  if (!eglMakeCurrent(static_cast<EGLDisplay>(display_), EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT))
    throw Error("eglMakeCurrent(no context) failed (" + egl_error() + ")");
}

std::string EglContext::describe() const { return renderer_ + " (" + version_ + ") via " + platform_; }

}  // namespace palpsim::render
