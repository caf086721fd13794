/**
 * Tile downloads and parses started without waiting for a frame (issue 19: first render and
 * full detail after a zoom).
 *
 * 3d-tiles-renderer 0.5.3 runs each of its queues (downloads per server, parses, external
 * tilesets) from a requestAnimationFrame callback, so every step of a tile's way waits for the
 * next frame: tileset → download → parse → draw is three frames or more, and a whole tablet's
 * external tilesets add two. With a renderer that draws on demand on a software GPU (a frame
 * of SwiftShader under load takes ~1 s) those waits were most of the time to the first tile.
 * The queues still batch: the jobs one update() adds are sorted and started together, from
 * a task queued after it (setTimeout 0) instead of the next frame.
 *
 * The queues are the renderer's shared module objects; `_schedulingCallback` is their
 * (unexported) hook, present in the pinned 0.5.3: where it is missing nothing changes.
 */

const soon = (run) => setTimeout(run, 0);

function prompt(queue) {
  if (!queue || !('_schedulingCallback' in queue) || queue._schedulingCallback === soon) return false;
  queue._schedulingCallback = soon;
  return true;
}

/**
 * Make a TilesRenderer's queues run their jobs in the next task instead of the next frame.
 * @param {import('3d-tiles-renderer/three').TilesRenderer} tiles
 */
export function runQueuesPromptly(tiles) {
  prompt(tiles.parseQueue);
  prompt(tiles.processNodeQueue);
  const downloads = tiles.downloadQueue;
  if (!downloads?.originQueues || downloads.dhPrompt) return;
  downloads.dhPrompt = true;
  // A queue per server origin, made by add() (which schedules its first run by frame):
  // switched on first sight, and that first run started now too.
  const add = downloads.add;
  downloads.add = function addPromptly(...args) {
    const result = add.apply(this, args);
    for (const queue of this.originQueues.values()) if (prompt(queue) && queue._runjobs) soon(queue._runjobs);
    return result;
  };
}
