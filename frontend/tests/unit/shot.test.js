import { describe, expect, it } from 'vitest';
import { crc32, pngText, pngWithText, shotMmPerPixel } from '../../src/viewer/shot.js';

// The smallest valid PNG: 1×1 grey, IHDR + IDAT + IEND.
const TINY = Uint8Array.from(
  atob('iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAAAAAA6fptVAAAACklEQVR4nGNgAAAAAgABSK+kcQAAAABJRU5ErkJggg=='),
  (c) => c.charCodeAt(0),
);

describe('PNG text metadata', () => {
  it('computes the PNG CRC (IEND chunk: AE 42 60 82)', () => {
    expect(crc32(new TextEncoder().encode('IEND'))).toBe(0xae426082);
  });

  it('inserts UTF-8 iTXt chunks after IHDR and reads them back', () => {
    const out = pngWithText(TINY, {
      Title: 'VAT 15245 (P000001), model 31 version 2',
      Copyright: 'https://creativecommons.org/licenses/by/4.0/',
      Comment: 'Puzriš-Dagan, scale bar 5 mm',
      Empty: '',
    });
    expect(out.length).toBeGreaterThan(TINY.length);
    expect(Array.from(out.subarray(0, 33))).toEqual(Array.from(TINY.subarray(0, 33))); // signature + IHDR
    expect(new TextDecoder().decode(out.subarray(37, 41))).toBe('iTXt');
    expect(Array.from(out.subarray(-12))).toEqual(Array.from(TINY.subarray(-12))); // IEND last
    expect(pngText(out)).toEqual({
      Title: 'VAT 15245 (P000001), model 31 version 2',
      Copyright: 'https://creativecommons.org/licenses/by/4.0/',
      Comment: 'Puzriš-Dagan, scale bar 5 mm',
    });
    expect(() => pngWithText(new Uint8Array(40), { a: 'b' })).toThrow(/not a PNG/);
  });
});

describe('screenshot scale', () => {
  it('keeps the vertical extent when the shot is at least as wide as the canvas', () => {
    // canvas 800×600 at 0.1 mm/px shows 60 mm tall; a 1920×1080 shot shows 60 mm over 1080 px
    expect(shotMmPerPixel({ mmPerScreenPx: 0.1, canvasW: 800, canvasH: 600, shotW: 1920, shotH: 1080 })).toBeCloseTo(60 / 1080, 12);
  });
  it('grows when the shot is narrower than the canvas (contain)', () => {
    // 80 mm wide canvas content must fit 600 px of a 600×600 shot
    expect(shotMmPerPixel({ mmPerScreenPx: 0.1, canvasW: 800, canvasH: 600, shotW: 600, shotH: 600 })).toBeCloseTo(80 / 600, 12);
  });
});
