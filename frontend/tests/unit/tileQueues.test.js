import { describe, expect, it } from 'vitest';
import { DownloadPriorityQueue, PriorityQueue } from '3d-tiles-renderer/core';
import { runQueuesPromptly } from '../../src/viewer/tileQueues.js';

const tick = () => new Promise((r) => setTimeout(r, 5));

describe('runQueuesPromptly', () => {
  it('runs parses and downloads in the next task, without a frame', async () => {
    // Frames that never come: unpatched queues would never run.
    globalThis.requestAnimationFrame ??= () => 0;
    globalThis.cancelAnimationFrame ??= () => {};
    const [a, b, c] = [{ n: 'a' }, { n: 'b' }, { n: 'c' }];
    const tiles = { parseQueue: new PriorityQueue(), processNodeQueue: new PriorityQueue(), downloadQueue: new DownloadPriorityQueue() };
    runQueuesPromptly(tiles);
    const ran = [];
    const parsed = tiles.parseQueue.add(a, (x) => ran.push(`parse ${x.n}`));
    const fetched = tiles.downloadQueue.add('http://example.org/t.glb', b, (x) => ran.push(`download ${x.n}`));
    expect(ran).toEqual([]); // batched: not inside add()
    await Promise.all([parsed, fetched]);
    await tick();
    expect(ran.sort()).toEqual(['download b', 'parse a']);
    // a second item on the same origin's queue runs too
    await tiles.downloadQueue.add('http://example.org/u.glb', c, (x) => ran.push(`download ${x.n}`));
    expect(ran).toContain('download c');
  });
});
