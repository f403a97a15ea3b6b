// Frames from the gateway: a binary WebSocket message is 4 bytes big-endian header
// length, the header as JSON, then the JPEG. Newest wins here too: while one frame is
// being decoded, only the newest that arrives meanwhile waits.

/** Splits a binary frame message into its header and a JPEG blob. */
export function parseFrame(buffer) {
  const n = new DataView(buffer).getUint32(0);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, n)));
  const jpeg = new Blob([new Uint8Array(buffer, 4 + n)], { type: "image/jpeg" });
  return { header, jpeg };
}

/** Draws frames into a canvas, decoding one at a time; onShown(header, now) after each. */
export class FrameSink {
  constructor(canvas, onShown) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.onShown = onShown;
    this.pending = null;
    this.busy = false;
    this.skipped = 0;
  }

  push(buffer) {
    if (this.pending) this.skipped += 1;
    this.pending = buffer;
    if (!this.busy) this.drain();
  }

  async drain() {
    this.busy = true;
    while (this.pending) {
      const { header, jpeg } = parseFrame(this.pending);
      this.pending = null;
      try {
        const bitmap = await createImageBitmap(jpeg);
        if (this.canvas.width !== bitmap.width || this.canvas.height !== bitmap.height) {
          this.canvas.width = bitmap.width;
          this.canvas.height = bitmap.height;
        }
        this.ctx.drawImage(bitmap, 0, 0);
        bitmap.close();
        this.onShown(header, performance.now());
      } catch (e) {
        console.error("a frame that does not decode", e);
      }
    }
    this.busy = false;
  }
}
