#include "render/frame_encoder.h"

#include <turbojpeg.h>

#include <chrono>
#include <string>

#include "core/error.h"
#include "render/backend_choice.h"

namespace palpsim::render {
namespace {

using Clock = std::chrono::steady_clock;

// A TurboJPEG compressor and its output buffer, kept across frames: after the first
// frame of a size nothing is allocated.
class TjCompressor {
 public:
  TjCompressor() : handle_(tjInitCompress()) {
    if (!handle_) throw Error(std::string("TurboJPEG: tjInitCompress failed: ") + tjGetErrorStr2(nullptr));
  }
  ~TjCompressor() {
    if (buf_) tjFree(buf_);
    tjDestroy(handle_);
  }
  TjCompressor(const TjCompressor&) = delete;
  TjCompressor& operator=(const TjCompressor&) = delete;

  // RGB8 rows top-down to a 4:2:0 JPEG in `out` (replaced)
  void encode(const std::uint8_t* rgb, int width, int height, int quality, std::vector<std::uint8_t>& out) {
    if (!rgb || width < 1 || height < 1)
      throw Error("TurboJPEG: nothing to encode (" + std::to_string(width) + " x " + std::to_string(height) + ")");
    if (quality < 1 || quality > 100) throw Error("TurboJPEG: quality " + std::to_string(quality) + " is outside 1..100");
    // the largest JPEG this size can give, so TurboJPEG never reallocates
    const unsigned long need = tjBufSize(width, height, TJSAMP_420);
    if (need > cap_) {
      if (buf_) tjFree(buf_);
      buf_ = tjAlloc(int(need));
      if (!buf_) throw Error("TurboJPEG: cannot allocate " + std::to_string(need) + " bytes");
      cap_ = need;
    }
    unsigned long size = cap_;
    if (tjCompress2(handle_, rgb, width, 0, height, TJPF_RGB, &buf_, &size, TJSAMP_420, quality,
                    TJFLAG_NOREALLOC) != 0)
      throw Error(std::string("TurboJPEG: tjCompress2 failed: ") + tjGetErrorStr2(handle_));
    out.assign(buf_, buf_ + size);
  }
  // frees the output buffer (the next frame makes it again)
  void release() {
    if (buf_) tjFree(buf_);
    buf_ = nullptr;
    cap_ = 0;
  }

 private:
  tjhandle handle_;
  unsigned char* buf_ = nullptr;
  unsigned long cap_ = 0;
};

// The CPU encoder: glReadPixels, then TurboJPEG.
class TurboJpegEncoder final : public FrameEncoder {
 public:
  const char* name() const override { return "turbojpeg"; }
  // one frame after another: the CPU does the work, nothing is gained by batching
  void encode_batch(FrameRenderer& r, const std::vector<EncodeJob>& jobs) override {
    for (const EncodeJob& j : jobs) {
      if (!j.out || !j.times) throw Error("jpeg encoder \"turbojpeg\": a job without output or times");
      r.read_rgb(j.target, rgb_, *j.times);
      const auto t0 = Clock::now();
      tj_.encode(rgb_.data(), r.width(j.target), r.height(j.target), j.quality, *j.out);
      j.times->encode_ms += std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
    }
  }
  void release_buffers() override {
    std::vector<std::uint8_t>().swap(rgb_);
    tj_.release();
  }

 private:
  std::vector<std::uint8_t> rgb_;  // the frame, reused
  TjCompressor tj_;
};

}  // namespace

FrameEncoderRegistry& frame_encoders() {
  static FrameEncoderRegistry registry;
  return registry;
}

std::unique_ptr<FrameEncoder> make_frame_encoder(JpegEncoderChoice choice, const EglContext& ctx, std::string* note) {
  const BackendChoice<FrameEncoder, JpegEncoderChoice> c{
      "jpeg encoder", JpegEncoderChoice::kCpu, JpegEncoderChoice::kNvjpeg, "turbojpeg",
      [] { return std::make_unique<TurboJpegEncoder>(); }, &frame_encoders()};
  return choose_backend(c, choice, ctx, note);
}

void encode_jpeg_rgb(const std::uint8_t* rgb, int width, int height, int quality, std::vector<std::uint8_t>& out) {
  // one compressor per thread, kept for the thread's life
  thread_local TjCompressor tj;
  tj.encode(rgb, width, height, quality, out);
}

bool decode_jpeg_rgb(const std::uint8_t* jpeg, std::size_t size, std::vector<std::uint8_t>& rgb, int& width,
                     int& height) {
  struct Handle {
    tjhandle h = tjInitDecompress();
    ~Handle() {
      if (h) tjDestroy(h);
    }
  };
  thread_local Handle d;
  if (!d.h || !jpeg || size == 0) return false;
  int w = 0, h = 0, subsamp = 0, colorspace = 0;
  if (tjDecompressHeader3(d.h, jpeg, static_cast<unsigned long>(size), &w, &h, &subsamp, &colorspace) != 0) return false;
  if (w < 1 || h < 1) return false;
  rgb.resize(std::size_t(w) * h * 3);
  if (tjDecompress2(d.h, jpeg, static_cast<unsigned long>(size), rgb.data(), w, 0, h, TJPF_RGB, 0) != 0) {
    // a warning (e.g. a truncated tail) still leaves usable pixels; an error does not
    if (tjGetErrorCode(d.h) != TJERR_WARNING) return false;
  }
  width = w;
  height = h;
  return true;
}

}  // namespace palpsim::render
