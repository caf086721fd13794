/**
 * Adaptive resolution while the camera moves (issue 19: ≥ 30 frames per second orbiting, even
 * on a software renderer): frames drawn during an interaction use a reduced pixel ratio, chosen
 * from the measured frame time, and one frame at full resolution is drawn when the camera has
 * been still for a moment. This is what the large-model viewers do: Cesium's
 * `resolutionScale`, Potree's and 3DHOP's lower-quality rendering while navigating.
 *
 * The cost of a frame in a fill-bound renderer (SwiftShader rasterises and shades on the CPU)
 * is proportional to its pixel count, i.e. to scale²; so the scale that meets a frame-time
 * target is scale · √(target / measured). Steps are bounded (at most halved or ×1.25 per
 * frame) so one slow frame (a texture upload, a shader compile) does not collapse the image.
 */

/** Frame time aimed at while moving: 30 frames per second. */
export const TARGET_FRAME_MS = 1000 / 30;
/** Smallest scale of the pixel ratio while moving (a quarter of the width and height). */
export const MIN_SCALE = 0.25;
/** Still time (ms) after which the full-resolution frame is drawn. */
export const SETTLE_MS = 200;
/** Longer intervals between two moving frames are pauses of the user, not frame cost. */
const MAX_MEASURED_MS = 10000;

/**
 * The next resolution scale (a factor of the pixel ratio, in [minScale, maxScale]) after a
 * frame drawn at `scale` took `frameMs`.
 * @param {number} scale the scale the frame was drawn at
 * @param {number} frameMs its duration, ms (time between two consecutive moving frames)
 * @param {{targetMs?: number, minScale?: number, maxScale?: number}} [options]
 * @returns {number}
 */
export function nextResolutionScale(scale, frameMs, { targetMs = TARGET_FRAME_MS, minScale = MIN_SCALE, maxScale = 1 } = {}) {
  if (!(scale > 0)) throw new RangeError(`scale must be > 0, got ${scale}`);
  if (!(targetMs > 0)) throw new RangeError(`targetMs must be > 0, got ${targetMs}`);
  if (!(frameMs > 0) || !Number.isFinite(frameMs)) return Math.min(maxScale, Math.max(minScale, scale));
  const step = Math.min(1.25, Math.max(0.5, Math.sqrt(targetMs / frameMs)));
  return Math.min(maxScale, Math.max(minScale, scale * step));
}

/**
 * The drawn scale for a learned one: the largest step of the ladder 1, 1/√2, 1/2, 1/(2√2), …
 * not above it (at least `minScale`). Each change of the pixel ratio resizes the canvas' drawing
 * buffer (its multisampled colour and depth buffers and the compositor's shared image are made
 * anew); a scale learned frame by frame changed it every frame. On the ladder a run of frames
 * keeps one size, and each step halves or doubles the pixels (docs/benchmarks.md, "Streaming
 * speed, session 8").
 * @param {number} scale in (0, 1]
 * @param {number} [minScale]
 */
export function quantizeScale(scale, minScale = MIN_SCALE) {
  if (!(scale > 0)) throw new RangeError(`scale must be > 0, got ${scale}`);
  if (scale >= 1) return 1;
  // Steps of √2 in scale are steps of 2 in pixels; the epsilon keeps 0.5 on its own step.
  const k = Math.ceil(-2 * Math.log2(scale) - 1e-9);
  return Math.max(minScale, 2 ** (-k / 2));
}

/**
 * The state of adaptive resolution for one viewer: call `moved()` when the camera moves under
 * the user's hand, `frame(timeMs)` at the start of each drawn frame (its requestAnimationFrame
 * time) to get the scale of the pixel ratio to draw it at. `onSettle` is called once the
 * camera has been still for `settleMs` after moving: the caller draws the full-resolution frame.
 * @param {{onSettle: () => void, settleMs?: number, targetMs?: number, minScale?: number,
 *   setTimer?: typeof setTimeout, clearTimer?: typeof clearTimeout}} options
 */
export function createAdaptiveResolution({
  onSettle,
  settleMs = SETTLE_MS,
  targetMs = TARGET_FRAME_MS,
  minScale = MIN_SCALE,
  setTimer = (f, ms) => setTimeout(f, ms),
  clearTimer = (t) => clearTimeout(t),
}) {
  let moving = false;
  let timer = null;
  // The scale learned from the frame times, kept between interactions: the next one starts there.
  let scale = 1;
  let lastMovingFrameMs = null;
  let movedSinceFrame = false;
  let enabled = true;
  // The last measured frame: "still" means no move for longer than a frame or two, not just
  // settleMs (a software renderer under load takes seconds a frame; a shorter wait would
  // draw a full-resolution frame between every two moves).
  let frameMs = 0;

  function settle() {
    timer = null;
    moving = false;
    onSettle();
  }

  return {
    /** The camera moved (a drag, a wheel step, a key held down). */
    moved() {
      if (!enabled) return;
      moving = true;
      movedSinceFrame = true;
      if (timer !== null) clearTimer(timer);
      timer = setTimer(settle, Math.max(settleMs, 2 * frameMs));
    },
    /**
     * A frame starts at `timeMs`: the scale of the pixel ratio to draw it at (1: full).
     * @param {number} timeMs
     */
    frame(timeMs) {
      // Consecutive moving frames measure the frame cost at the scale drawn last; a frame
      // without a move (the user paused) ends the run.
      if (lastMovingFrameMs !== null && movedSinceFrame) {
        const dt = timeMs - lastMovingFrameMs;
        if (dt > 0 && dt < MAX_MEASURED_MS) {
          scale = nextResolutionScale(scale, dt, { targetMs, minScale });
          frameMs = dt;
        }
      }
      lastMovingFrameMs = movedSinceFrame ? timeMs : null;
      movedSinceFrame = false;
      return moving ? quantizeScale(scale, minScale) : 1;
    },
    /** Off: every frame at full resolution (e.g. for pixel-exact tests); on again with true. */
    setEnabled(on) {
      enabled = Boolean(on);
      if (!enabled && moving) {
        if (timer !== null) clearTimer(timer);
        settle();
      }
    },
    get moving() {
      return moving;
    },
    get scale() {
      return scale;
    },
    dispose() {
      if (timer !== null) clearTimer(timer);
      timer = null;
    },
  };
}
