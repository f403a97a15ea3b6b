// The CUDA side of rendering (cuda/render_interop.h): the "nvjpeg" frame encoder and
// the "cuda-gl" overlay writer, both through CUDA-OpenGL interop on the render thread,
// whose EGL context must be current whenever they are made, used or destroyed.
//
// GL texture names are reused by the driver once a texture is deleted, so a cached
// registration keyed by name alone could outlive its texture and silently map the old
// storage. Every registration therefore tags its texture with a unique debug label
// (glObjectLabel, core since GL 4.3) and is trusted only while the texture at that name
// still carries the label; otherwise the texture is registered again.
#define GL_GLEXT_PROTOTYPES 1
#include <GL/gl.h>
#include <GL/glext.h>

#include <cuda_gl_interop.h>
#include <cuda_runtime.h>
#include <nvjpeg.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <map>
#include <string>
#include <vector>

#include "core/error.h"
#include "cuda/check.h"
#include "cuda/register_backends.h"
#include "cuda/render_interop.h"

namespace palpsim::cuda {

namespace {

// ---- nvJPEG status checks ----

// the enum's name of an nvJPEG status, for error messages
const char* nvjpeg_status_name(nvjpegStatus_t s) {
  switch (s) {
    case NVJPEG_STATUS_SUCCESS: return "NVJPEG_STATUS_SUCCESS";
    case NVJPEG_STATUS_NOT_INITIALIZED: return "NVJPEG_STATUS_NOT_INITIALIZED";
    case NVJPEG_STATUS_INVALID_PARAMETER: return "NVJPEG_STATUS_INVALID_PARAMETER";
    case NVJPEG_STATUS_BAD_JPEG: return "NVJPEG_STATUS_BAD_JPEG";
    case NVJPEG_STATUS_JPEG_NOT_SUPPORTED: return "NVJPEG_STATUS_JPEG_NOT_SUPPORTED";
    case NVJPEG_STATUS_ALLOCATOR_FAILURE: return "NVJPEG_STATUS_ALLOCATOR_FAILURE";
    case NVJPEG_STATUS_EXECUTION_FAILED: return "NVJPEG_STATUS_EXECUTION_FAILED";
    case NVJPEG_STATUS_ARCH_MISMATCH: return "NVJPEG_STATUS_ARCH_MISMATCH";
    case NVJPEG_STATUS_INTERNAL_ERROR: return "NVJPEG_STATUS_INTERNAL_ERROR";
    case NVJPEG_STATUS_IMPLEMENTATION_NOT_SUPPORTED: return "NVJPEG_STATUS_IMPLEMENTATION_NOT_SUPPORTED";
    case NVJPEG_STATUS_INCOMPLETE_BITSTREAM: return "NVJPEG_STATUS_INCOMPLETE_BITSTREAM";
  }
  return "unknown nvjpegStatus_t";
}

// throws palpsim::Error naming the nvJPEG call, its status and the source line
void check_nvjpeg(nvjpegStatus_t s, const char* call, const char* file, int line) {
  if (s != NVJPEG_STATUS_SUCCESS)
    throw Error(std::string("nvJPEG error ") + nvjpeg_status_name(s) + " (" + std::to_string(int(s)) + ") in " +
                call + " at " + file + ":" + std::to_string(line));
}

#define PALPSIM_NVJPEG_CHECK(call) check_nvjpeg((call), #call, __FILE__, __LINE__)

// ---- GL texture identity (see the top of the file) ----

// a label no other texture of this process carries
std::string next_label(const char* what) {
  static std::atomic<unsigned long long> serial{0};
  return std::string("palpsim ") + what + " #" + std::to_string(++serial);
}

// gives texture `tex` the label (it must be a texture object)
void tag_texture(GLuint tex, const std::string& label) {
  glObjectLabel(GL_TEXTURE, tex, GLsizei(label.size()), label.c_str());
}

// true when `tex` names a texture that still carries `label`; glIsTexture first, so
// that a deleted name makes no GL error for the renderer's own error checks to find
bool texture_has_label(GLuint tex, const std::string& label) {
  if (tex == 0 || label.empty() || glIsTexture(tex) != GL_TRUE) return false;
  char buf[128];
  GLsizei len = 0;
  glGetObjectLabel(GL_TEXTURE, tex, GLsizei(sizeof buf), &len, buf);
  return len >= 0 && std::size_t(len) == label.size() && std::memcmp(buf, label.data(), label.size()) == 0;
}

// ---- CUDA-GL interop helpers ----

// Throws when the GL context is on a CUDA device other than the current one (then J
// in device memory and the texture would live on different GPUs). cudaGLGetDevices may
// not be answerable for every EGL context; an error or an empty answer from it is
// cleared and the check skipped, since a wrong device then shows up as a failing
// registration, named.
void check_gl_device(const char* who) {
  unsigned n = 0;
  int devices[16] = {};
  const cudaError_t e = cudaGLGetDevices(&n, devices, 16, cudaGLDeviceListAll);
  if (e != cudaSuccess || n == 0) {
    cudaGetLastError();  // not sticky: clear it so that later checks start clean
    return;
  }
  int current = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&current));
  for (unsigned i = 0; i < std::min(n, 16u); ++i)
    if (devices[i] == current) return;
  throw Error(std::string(who) + ": the GL context is not on CUDA device " + std::to_string(current) +
              " (the device the deformation's J lives on); CUDA-GL interop needs both on one GPU");
}

// Unregisters a resource on a cleanup path (destructor, stale entry, re-registration):
// errors are cleared, not thrown, since the texture may already be deleted by the
// renderer and nothing is left to undo. GL errors the driver may post for a deleted
// texture are drained too: the renderer clears and checks GL errors after each of its
// own steps, so none of its own are pending here, and it would blame itself for ours.
void unregister_quietly(cudaGraphicsResource_t res) {
  if (!res) return;
  if (cudaGraphicsUnregisterResource(res) != cudaSuccess) cudaGetLastError();
  for (int i = 0; i < 32 && glGetError() != GL_NO_ERROR; ++i) {
  }
}

// One mapping of registered resources on a stream, all in one call (one hand-over
// from GL to CUDA however many there are): unmap() ends it (checked); the destructor
// unmaps on an error path so that GL never keeps a resource CUDA still maps.
class Mapping {
 public:
  Mapping(std::vector<cudaGraphicsResource_t> res, cudaStream_t stream) : res_(std::move(res)), stream_(stream) {
    if (!res_.empty()) PALPSIM_CUDA_CHECK(cudaGraphicsMapResources(int(res_.size()), res_.data(), stream_));
  }
  Mapping(cudaGraphicsResource_t res, cudaStream_t stream) : Mapping(std::vector<cudaGraphicsResource_t>{res}, stream) {}
  ~Mapping() {
    if (!res_.empty() && cudaGraphicsUnmapResources(int(res_.size()), res_.data(), stream_) != cudaSuccess)
      cudaGetLastError();
  }
  Mapping(const Mapping&) = delete;
  Mapping& operator=(const Mapping&) = delete;

  /// The i-th mapped texture's level 0 as a CUDA array.
  cudaArray_t array(std::size_t i = 0) const {
    cudaArray_t a = nullptr;
    PALPSIM_CUDA_CHECK(cudaGraphicsSubResourceGetMappedArray(&a, res_.at(i), 0, 0));
    return a;
  }
  /// Ends the mapping; work issued on the stream before it completes before later GL work.
  void unmap() {
    std::vector<cudaGraphicsResource_t> r;
    r.swap(res_);
    if (!r.empty()) PALPSIM_CUDA_CHECK(cudaGraphicsUnmapResources(int(r.size()), r.data(), stream_));
  }

 private:
  std::vector<cudaGraphicsResource_t> res_;
  cudaStream_t stream_;
};

// milliseconds since t0
double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

// ---- RGBA8 -> interleaved RGB ----

// drops alpha: pixel p of the RGBA rows (pitch width*4) to bytes 3p..3p+2
__global__ void rgba_to_rgb_kernel(const uchar4* __restrict__ rgba, std::uint8_t* __restrict__ rgb, unsigned n) {
  for (unsigned p = blockIdx.x * blockDim.x + threadIdx.x; p < n; p += gridDim.x * blockDim.x) {
    const uchar4 c = rgba[p];
    rgb[3 * p + 0] = c.x;
    rgb[3 * p + 1] = c.y;
    rgb[3 * p + 2] = c.z;
  }
}

// ===================================================================================
// The "nvjpeg" frame encoder.
// ===================================================================================

class NvjpegFrameEncoder final : public render::FrameEncoder {
 public:
  NvjpegFrameEncoder() {
    try {
      check_gl_device("jpeg encoder \"nvjpeg\"");
      PALPSIM_CUDA_CHECK(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking));
      PALPSIM_NVJPEG_CHECK(nvjpegCreateSimple(&handle_));
    } catch (...) {
      release();
      throw;
    }
  }
  ~NvjpegFrameEncoder() override { release(); }

  const char* name() const override { return "nvjpeg"; }

  // All jobs' textures are mapped in one call and copied out, then every frame is
  // converted and encoded on one stream, and the stream is waited for once before the
  // bitstreams are fetched: two hand-overs between GL and CUDA per batch, not per frame.
  void encode_batch(render::FrameRenderer& r, const std::vector<render::EncodeJob>& jobs) override {
    if (jobs.empty()) return;
    std::vector<Slot*> slots;
    std::vector<cudaGraphicsResource_t> res;
    for (const render::EncodeJob& j : jobs) {
      if (!j.out || !j.times) throw Error("jpeg encoder \"nvjpeg\": a job without output or times");
      if (j.quality < 1 || j.quality > 100)
        throw Error("jpeg encoder \"nvjpeg\": quality = " + std::to_string(j.quality) + " is outside 1..100");
      const int w = r.width(j.target), h = r.height(j.target);
      if (w <= 0 || h <= 0) throw Error("jpeg encoder \"nvjpeg\": the renderer has no frame to encode yet");
      Slot& s = bind_texture(j.target, r.color_texture(j.target), w, h);
      if (std::find(slots.begin(), slots.end(), &s) != slots.end())
        throw Error("jpeg encoder \"nvjpeg\": target " + std::to_string(j.target) + " appears twice in one batch");
      slots.push_back(&s);
      res.push_back(s.res);
    }
    const double share = 1.0 / double(jobs.size());

    // readback: map every colour texture, copy its w x h texels out, unmap
    const auto t0 = std::chrono::steady_clock::now();
    {
      Mapping m(res, stream_);
      for (std::size_t i = 0; i < slots.size(); ++i) {
        const Slot& s = *slots[i];
        PALPSIM_CUDA_CHECK(cudaMemcpy2DFromArrayAsync(s.d_rgba, std::size_t(s.w) * 4, m.array(i), 0, 0,
                                                      std::size_t(s.w) * 4, std::size_t(s.h),
                                                      cudaMemcpyDeviceToDevice, stream_));
      }
      m.unmap();
    }
    const auto t1 = std::chrono::steady_clock::now();
    for (const render::EncodeJob& j : jobs)
      j.times->readback_ms += share * std::chrono::duration<double, std::milli>(t1 - t0).count();

    // encode: drop alpha, nvJPEG from the RGB rows, every frame queued before one wait
    for (std::size_t i = 0; i < slots.size(); ++i) {
      Slot& s = *slots[i];
      const unsigned n = unsigned(s.w) * unsigned(s.h);
      const unsigned threads = 256, blocks = (n + threads - 1) / threads;
      rgba_to_rgb_kernel<<<blocks, threads, 0, stream_>>>(reinterpret_cast<const uchar4*>(s.d_rgba), s.d_rgb, n);
      PALPSIM_CUDA_CHECK(cudaGetLastError());
      if (jobs[i].quality != s.quality) {
        PALPSIM_NVJPEG_CHECK(nvjpegEncoderParamsSetQuality(s.params, jobs[i].quality, stream_));
        s.quality = jobs[i].quality;
      }
      nvjpegImage_t img{};
      img.channel[0] = s.d_rgb;
      img.pitch[0] = std::size_t(s.w) * 3;
      PALPSIM_NVJPEG_CHECK(nvjpegEncodeImage(handle_, s.state, s.params, &img, NVJPEG_INPUT_RGBI, s.w, s.h, stream_));
    }
    PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
    // the bitstreams into pinned host memory, one after another
    for (std::size_t i = 0; i < slots.size(); ++i) {
      Slot& s = *slots[i];
      std::size_t length = 0;
      PALPSIM_NVJPEG_CHECK(nvjpegEncodeRetrieveBitstream(handle_, s.state, nullptr, &length, stream_));
      if (length > jpeg_cap_) grow_host(length);  // rare: presized by nvjpegEncodeGetBufferSize
      PALPSIM_NVJPEG_CHECK(nvjpegEncodeRetrieveBitstream(handle_, s.state, h_jpeg_, &length, stream_));
      PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
      jobs[i].out->assign(h_jpeg_, h_jpeg_ + length);
    }
    const double encode_ms = ms_since(t1);
    for (const render::EncodeJob& j : jobs) j.times->encode_ms += share * encode_ms;
  }

 private:
  // One target's registered colour texture, its device buffers and nvJPEG state.
  struct Slot {
    cudaGraphicsResource_t res = nullptr;
    GLuint tex = 0;
    int w = 0, h = 0;
    std::string label;
    std::uint8_t* d_rgba = nullptr;  // the frame's texels, rows of w*4 bytes
    std::uint8_t* d_rgb = nullptr;   // the frame as interleaved RGB, rows of w*3 bytes
    std::size_t pixels_cap = 0;      // pixels both device buffers hold
    nvjpegEncoderState_t state = nullptr;
    nvjpegEncoderParams_t params = nullptr;
    int quality = -1;                // quality set in params
  };

  // frees a slot's registration, buffers and nvJPEG objects; errors ignored
  static void free_slot(Slot& s) noexcept {
    unregister_quietly(s.res);
    if (s.params) nvjpegEncoderParamsDestroy(s.params);
    if (s.state) nvjpegEncoderStateDestroy(s.state);
    cudaFree(s.d_rgba);
    cudaFree(s.d_rgb);
    cudaGetLastError();
    s = Slot{};
  }

  // frees everything; errors ignored (destructor and failed constructor)
  void release() noexcept {
    for (auto& [t, s] : slots_) free_slot(s);
    slots_.clear();
    if (handle_) nvjpegDestroy(handle_);
    handle_ = nullptr;
    cudaFreeHost(h_jpeg_);
    h_jpeg_ = nullptr;
    jpeg_cap_ = 0;
    if (stream_) cudaStreamDestroy(stream_);
    stream_ = nullptr;
    cudaGetLastError();
  }

  // the pinned bitstream buffer, at least `bytes` long (its contents are not kept)
  void grow_host(std::size_t bytes) {
    if (h_jpeg_) PALPSIM_CUDA_CHECK(cudaFreeHost(h_jpeg_));
    h_jpeg_ = nullptr;
    jpeg_cap_ = 0;
    PALPSIM_CUDA_CHECK(cudaMallocHost(&h_jpeg_, bytes));
    jpeg_cap_ = bytes;
  }

  // Target t's slot, its colour texture registered when it is not the one registered:
  // another name, another size, or the same name now naming another texture (no
  // label). Slots of textures that are gone (removed targets) are freed then too.
  // Device buffers grow here, never per frame. Nothing is kept of a registration that
  // fails a check, so the next frame tries again.
  Slot& bind_texture(render::FrameRenderer::TargetId t, GLuint tex, int w, int h) {
    Slot& s = slots_[t];
    if (s.res && tex == s.tex && w == s.w && h == s.h && texture_has_label(tex, s.label)) return s;
    unregister_quietly(s.res);
    s.res = nullptr;
    s.tex = 0;
    s.w = s.h = 0;
    s.label.clear();
    for (auto i = slots_.begin(); i != slots_.end();) {
      if (i->first == t || texture_has_label(i->second.tex, i->second.label)) {
        ++i;
      } else {
        free_slot(i->second);
        i = slots_.erase(i);
      }
    }
    if (tex == 0 || glIsTexture(tex) != GL_TRUE)
      throw Error("jpeg encoder \"nvjpeg\": FrameRenderer::color_texture(" + std::to_string(t) + ") = " +
                  std::to_string(tex) + " is not a GL texture");
    if (!s.state) PALPSIM_NVJPEG_CHECK(nvjpegEncoderStateCreate(handle_, &s.state, stream_));
    if (!s.params) {
      PALPSIM_NVJPEG_CHECK(nvjpegEncoderParamsCreate(handle_, &s.params, stream_));
      // 4:2:0 chroma and baseline Huffman tables, as the CPU encoder (libjpeg-turbo)
      PALPSIM_NVJPEG_CHECK(nvjpegEncoderParamsSetSamplingFactors(s.params, NVJPEG_CSS_420, stream_));
      PALPSIM_NVJPEG_CHECK(nvjpegEncoderParamsSetOptimizedHuffman(s.params, 0, stream_));
      s.quality = -1;
    }
    cudaGraphicsResource_t res = nullptr;
    const cudaError_t e = cudaGraphicsGLRegisterImage(&res, tex, GL_TEXTURE_2D, cudaGraphicsRegisterFlagsReadOnly);
    if (e != cudaSuccess) {
      cudaGetLastError();
      throw Error(std::string("jpeg encoder \"nvjpeg\": cudaGraphicsGLRegisterImage of the colour texture ") +
                  std::to_string(tex) + " (GL_TEXTURE_2D, GL_RGBA8, " + std::to_string(w) + "x" + std::to_string(h) +
                  ") failed: " + cudaGetErrorName(e) + " (" + cudaGetErrorString(e) +
                  "); it must be a complete texture (e.g. immutable storage of one level) on the CUDA device");
    }
    try {
      // the texture must hold at least the frame, as 4 x 8-bit texels
      {
        Mapping m(res, stream_);
        cudaChannelFormatDesc d{};
        cudaExtent ext{};
        unsigned flags = 0;
        PALPSIM_CUDA_CHECK(cudaArrayGetInfo(&d, &ext, &flags, m.array()));
        m.unmap();
        // only the texel layout matters to the copy: four 8-bit channels (the kind, plain
        // or normalised unsigned, depends on the driver's mapping of GL_RGBA8)
        if (d.x != 8 || d.y != 8 || d.z != 8 || d.w != 8)
          throw Error("jpeg encoder \"nvjpeg\": the colour texture is not GL_RGBA8 (CUDA sees channels of " +
                      std::to_string(d.x) + "/" + std::to_string(d.y) + "/" + std::to_string(d.z) + "/" +
                      std::to_string(d.w) + " bits, kind " + std::to_string(int(d.f)) + ")");
        if (ext.width < std::size_t(w) || ext.height < std::size_t(h))
          throw Error("jpeg encoder \"nvjpeg\": the colour texture (" + std::to_string(ext.width) + "x" +
                      std::to_string(ext.height) + ") is smaller than the frame (" + std::to_string(w) + "x" +
                      std::to_string(h) + ")");
      }
      // device buffers for the frame, grown only
      const std::size_t pixels = std::size_t(w) * std::size_t(h);
      if (pixels > s.pixels_cap) {
        PALPSIM_CUDA_CHECK(cudaFree(s.d_rgba));
        PALPSIM_CUDA_CHECK(cudaFree(s.d_rgb));
        s.d_rgba = s.d_rgb = nullptr;
        s.pixels_cap = 0;
        PALPSIM_CUDA_CHECK(cudaMalloc(&s.d_rgba, pixels * 4));
        PALPSIM_CUDA_CHECK(cudaMalloc(&s.d_rgb, pixels * 3));
        s.pixels_cap = pixels;
      }
      // the pinned bitstream buffer, as large as nvJPEG says a frame of this size may need
      std::size_t most = 0;
      PALPSIM_NVJPEG_CHECK(nvjpegEncodeGetBufferSize(handle_, s.params, w, h, &most));
      if (most > jpeg_cap_) grow_host(most);
    } catch (...) {
      unregister_quietly(res);
      throw;
    }
    // committed: this texture, tagged so that a reused name is noticed
    s.res = res;
    s.tex = tex;
    s.w = w;
    s.h = h;
    s.label = next_label("nvjpeg colour");
    tag_texture(tex, s.label);
    return s;
  }

  cudaStream_t stream_ = nullptr;
  nvjpegHandle_t handle_ = nullptr;
  std::map<render::FrameRenderer::TargetId, Slot> slots_;
  std::uint8_t* h_jpeg_ = nullptr;        // pinned bitstream, shared by the slots
  std::size_t jpeg_cap_ = 0;
};

// ===================================================================================
// The "cuda-gl" overlay writer.
// ===================================================================================

class CudaGlOverlayWriter final : public render::OverlayWriter {
 public:
  CudaGlOverlayWriter() {
    check_gl_device("overlay writer \"cuda-gl\"");
    PALPSIM_CUDA_CHECK(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking));
  }
  ~CudaGlOverlayWriter() override {
    // on the render thread, its context current (the render worker destroys it there)
    for (auto& [tex, e] : regs_) unregister_quietly(e.res);
    regs_.clear();
    if (stream_) cudaStreamDestroy(stream_);
    cudaGetLastError();
  }

  const char* name() const override { return "cuda-gl"; }

  // Checks every write first, then maps all the textures that take a device copy in
  // one call, copies, unmaps and waits once: one hand-over between GL and CUDA per batch.
  void write_batch(render::FrameRenderer& r, const std::vector<render::OverlayWrite>& writes) override {
    struct Copy {
      render::FrameRenderer::OverlayId id;
      cudaGraphicsResource_t res;
      const render::OverlaySource* src;
    };
    std::vector<Copy> copies;
    for (std::size_t n = 0; n < writes.size(); ++n) {
      const render::FrameRenderer::OverlayId id = writes[n].id;
      const render::OverlaySource& src = writes[n].src;
      // a later write of the same overlay wins
      bool later = false;
      for (std::size_t m = n + 1; m < writes.size(); ++m) later = later || writes[m].id == id;
      if (later) continue;
      const render::Voi& voi = src.voi;
      // undeformed: the overlay shows nothing
      if (voi.count() == 0) {
        r.clear_overlay(id);
        continue;
      }
      // Fallback: J only in host memory (the deformation ran on the cpu backend, or its
      // device copy failed): the plain sub-box upload, as the "upload" writer does.
      if (!src.device_j) {
        if (!src.host_j)
          throw Error("overlay writer \"cuda-gl\": J on a VOI of " + std::to_string(voi.count()) +
                      " voxels has neither a device nor a host copy");
        r.upload_overlay(id, voi, src.host_j);
        continue;
      }
      const std::size_t bytes = std::size_t(voi.count()) * sizeof(float);
      if (src.device_j->size() < bytes || !src.device_j->data())
        throw Error("overlay writer \"cuda-gl\": the device copy of J holds " + std::to_string(src.device_j->size()) +
                    " bytes, the VOI needs " + std::to_string(bytes));
      const Entry& e = registration(r.overlay_texture(id));
      if (std::size_t(voi.size.x) > e.extent.width || std::size_t(voi.size.y) > e.extent.height ||
          std::size_t(voi.size.z) > e.extent.depth)
        throw Error("overlay writer \"cuda-gl\": a VOI of " + std::to_string(voi.size.x) + "x" +
                    std::to_string(voi.size.y) + "x" + std::to_string(voi.size.z) + " exceeds the overlay texture (" +
                    std::to_string(e.extent.width) + "x" + std::to_string(e.extent.height) + "x" +
                    std::to_string(e.extent.depth) + ")");
      copies.push_back({id, e.res, &src});
    }
    if (copies.empty()) return;

    // J (i fastest, rows of voi.size.x floats) into texels (0..size) of each mapped texture
    {
      std::vector<cudaGraphicsResource_t> res;
      for (const Copy& c : copies) res.push_back(c.res);
      Mapping m(res, stream_);
      for (std::size_t i = 0; i < copies.size(); ++i) {
        const render::OverlaySource& src = *copies[i].src;
        const render::Voi& voi = src.voi;
        cudaMemcpy3DParms p{};
        p.srcPtr = make_cudaPitchedPtr(const_cast<void*>(src.device_j->data()), std::size_t(voi.size.x) * sizeof(float),
                                       std::size_t(voi.size.x), std::size_t(voi.size.y));
        p.dstArray = m.array(i);
        p.dstPos = make_cudaPos(0, 0, 0);
        p.extent = make_cudaExtent(std::size_t(voi.size.x), std::size_t(voi.size.y), std::size_t(voi.size.z));
        p.kind = cudaMemcpyDeviceToDevice;
        PALPSIM_CUDA_CHECK(cudaMemcpy3DAsync(&p, stream_));
      }
      m.unmap();
    }
    // Unmapping orders the copies before later GL work; waiting also frees the sources
    // for the deformation worker to reuse as soon as this returns, and makes the time honest.
    PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
    for (const Copy& c : copies) r.set_overlay_box(c.id, c.src->voi);
  }

 private:
  // one registered overlay texture
  struct Entry {
    cudaGraphicsResource_t res = nullptr;
    std::string label;
    cudaExtent extent{};  // texels
  };

  // The registration of overlay texture `tex`, made on first use or when the name now
  // names another texture. A new registration also drops entries whose texture is gone.
  const Entry& registration(GLuint tex) {
    auto it = regs_.find(tex);
    if (it != regs_.end() && texture_has_label(tex, it->second.label)) return it->second;
    if (it != regs_.end()) {
      unregister_quietly(it->second.res);
      regs_.erase(it);
    }
    for (auto i = regs_.begin(); i != regs_.end();) {
      if (texture_has_label(i->first, i->second.label)) {
        ++i;
      } else {
        unregister_quietly(i->second.res);
        i = regs_.erase(i);
      }
    }
    if (tex == 0 || glIsTexture(tex) != GL_TRUE)
      throw Error("overlay writer \"cuda-gl\": FrameRenderer::overlay_texture() = " + std::to_string(tex) +
                  " is not a GL texture");
    Entry e;
    const cudaError_t err =
        cudaGraphicsGLRegisterImage(&e.res, tex, GL_TEXTURE_3D, cudaGraphicsRegisterFlagsSurfaceLoadStore);
    if (err != cudaSuccess) {
      cudaGetLastError();
      throw Error(std::string("overlay writer \"cuda-gl\": cudaGraphicsGLRegisterImage of overlay texture ") +
                  std::to_string(tex) + " (GL_TEXTURE_3D, GL_R32F) failed: " + cudaGetErrorName(err) + " (" +
                  cudaGetErrorString(err) + "); it must be a complete texture on the CUDA device");
    }
    // the texture must be single-channel 32-bit float; its extent bounds the VOI
    try {
      Mapping m(e.res, stream_);
      cudaChannelFormatDesc d{};
      unsigned flags = 0;
      PALPSIM_CUDA_CHECK(cudaArrayGetInfo(&d, &e.extent, &flags, m.array()));
      m.unmap();
      if (d.x != 32 || d.y != 0 || d.z != 0 || d.w != 0 || d.f != cudaChannelFormatKindFloat)
        throw Error("overlay writer \"cuda-gl\": overlay texture " + std::to_string(tex) +
                    " is not GL_R32F (CUDA sees channels of " + std::to_string(d.x) + "/" + std::to_string(d.y) + "/" +
                    std::to_string(d.z) + "/" + std::to_string(d.w) + " bits)");
    } catch (...) {
      unregister_quietly(e.res);
      throw;
    }
    e.label = next_label("cuda-gl overlay");
    tag_texture(tex, e.label);
    return regs_[tex] = e;
  }

  cudaStream_t stream_ = nullptr;
  std::map<GLuint, Entry> regs_;  // registered overlay textures by GL name
};

}  // namespace

std::unique_ptr<render::FrameEncoder> make_nvjpeg_frame_encoder() { return std::make_unique<NvjpegFrameEncoder>(); }

std::unique_ptr<render::OverlayWriter> make_cuda_overlay_writer() { return std::make_unique<CudaGlOverlayWriter>(); }

bool cuda_render_available(std::string* why) {
  int n = 0;
  const cudaError_t e = cudaGetDeviceCount(&n);
  if (e != cudaSuccess || n == 0) {
    if (why)
      *why = e != cudaSuccess ? std::string("no CUDA device (") + cudaGetErrorString(e) + ")" : "no CUDA device found";
    cudaGetLastError();  // clear the error so that later calls start clean
    return false;
  }
  int dev = 0;
  cudaDeviceProp prop{};
  if (cudaGetDevice(&dev) != cudaSuccess || cudaGetDeviceProperties(&prop, dev) != cudaSuccess) {
    cudaGetLastError();
    if (why) *why = "cudaGetDeviceProperties failed";
    return false;
  }
  if (why) *why = "CUDA device " + std::to_string(dev) + ": " + prop.name;
  return true;
}

void register_render_backends() {
  render::frame_encoders().add(JpegEncoderChoice::kNvjpeg, {cuda_render_available, make_nvjpeg_frame_encoder});
  render::overlay_writers().add(OverlayWriterChoice::kCudaGl, {cuda_render_available, make_cuda_overlay_writer});
}

}  // namespace palpsim::cuda
