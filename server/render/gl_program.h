// The GL helpers of the frame renderer: error checks and a linked program with its
// uniform locations (needs a current OpenGL 4.5 context).
#pragma once

#define GL_GLEXT_PROTOTYPES
#include <GL/glcorearb.h>

#include <string>
#include <unordered_map>

#include "core/vec3.h"

namespace palpsim::render {

/// The pending GL errors as text, or "" when there is none (clears them).
std::string gl_errors();
/// Throws palpsim::Error naming `what` when GL has errors pending.
void check_gl(const char* what);

/// A linked GL program with its uniform locations looked up once by name.
struct Program {
  GLuint id = 0;
  std::unordered_map<std::string, GLint> loc;

  /// Compiles and links a full-viewport triangle with fragment shader `fs`, or (compute)
  /// a compute shader; throws palpsim::Error with the compiler's log, naming `name`.
  void build(const std::string& fs, const char* name, bool compute = false);
  /// The location of a uniform (-1, which GL ignores, when the compiler removed it).
  GLint operator[](const std::string& name) {
    auto it = loc.find(name);
    if (it != loc.end()) return it->second;
    return loc[name] = glGetUniformLocation(id, name.c_str());
  }
  /// Sets uniform `n` of the program in use (float, vec2, vec3, vec4).
  void set(const char* n, float a) { glUniform1f((*this)[n], a); }
  void set(const char* n, float a, float b) { glUniform2f((*this)[n], a, b); }
  void set(const char* n, const Vec3& v) { glUniform3f((*this)[n], float(v.x), float(v.y), float(v.z)); }
  void set(const char* n, float a, float b, float c, float d) { glUniform4f((*this)[n], a, b, c, d); }
};

}  // namespace palpsim::render
