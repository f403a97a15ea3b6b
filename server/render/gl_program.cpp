// The frame renderer's GL helpers (gl_program.h).
#include "render/gl_program.h"

#include <algorithm>
#include <cstdio>

#include "core/error.h"
#include "render/shaders.h"

namespace palpsim::render {
namespace {

// a compiled shader of `src`, or an error with the compiler's log
GLuint compile(GLenum type, const std::string& src, const char* name) {
  const GLuint s = glCreateShader(type);
  const char* p = src.c_str();
  glShaderSource(s, 1, &p, nullptr);
  glCompileShader(s);
  GLint ok = 0;
  glGetShaderiv(s, GL_COMPILE_STATUS, &ok);
  if (!ok) {
    GLint n = 0;
    glGetShaderiv(s, GL_INFO_LOG_LENGTH, &n);
    std::string log(std::size_t(std::max(n, 1)), '\0');
    glGetShaderInfoLog(s, n, nullptr, log.data());
    glDeleteShader(s);
    throw Error(std::string("the ") + name + " shader does not compile: " + log);
  }
  return s;
}

}  // namespace

std::string gl_errors() {
  std::string s;
  GLenum e;
  for (int n = 0; n < 8 && (e = glGetError()) != GL_NO_ERROR; ++n) {
    char b[16];
    std::snprintf(b, sizeof b, "0x%04X", unsigned(e));
    s += (s.empty() ? "" : ", ") + std::string(b) + (e == GL_OUT_OF_MEMORY ? " (out of memory)" : "");
  }
  return s;
}

void check_gl(const char* what) {
  const std::string e = gl_errors();
  if (!e.empty()) throw Error(std::string("OpenGL error during ") + what + ": " + e);
}

void Program::build(const std::string& fs, const char* name, bool compute) {
  const GLuint v = compute ? 0 : compile(GL_VERTEX_SHADER, shaders::kFullscreenVs, name);
  const GLuint f = compile(compute ? GL_COMPUTE_SHADER : GL_FRAGMENT_SHADER, fs, name);
  id = glCreateProgram();
  if (v) glAttachShader(id, v);
  glAttachShader(id, f);
  glLinkProgram(id);
  if (v) glDeleteShader(v);
  glDeleteShader(f);
  GLint ok = 0;
  glGetProgramiv(id, GL_LINK_STATUS, &ok);
  if (!ok) {
    GLint n = 0;
    glGetProgramiv(id, GL_INFO_LOG_LENGTH, &n);
    std::string log(std::size_t(std::max(n, 1)), '\0');
    glGetProgramInfoLog(id, n, nullptr, log.data());
    throw Error(std::string("the ") + name + " shader does not link: " + log);
  }
}

}  // namespace palpsim::render
