import { describe, expect, it } from 'vitest';
import { lightDirection } from '../../src/viewer/light.js';
import { nearestPhoto } from '../../src/viewer/photos.js';
import { faceFrames, faceInView, scanToTabletDir, scanToTabletPoint, tabletToScanDir } from '../../src/viewer/photoFaces.js';

// Rotations of the scan frame into the tablet frame for a tablet turned over its bottom edge
// (the reverse: x kept, y and z flipped) and turned about y by 90° (an edge).
const I = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
const REVERSE = [[1, 0, 0], [0, -1, 0], [0, 0, -1]];
const EDGE = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]];
const transforms = {
  scans: {
    'sim-0-obverse': { rotation: I, translation_mm: [0, 0, 0] },
    'sim-0-reverse': { rotation: REVERSE, translation_mm: [0, 40, 20] },
    'sim-0-left': { rotation: EDGE, translation_mm: [-5, 0, 10] },
  },
};
const report = {
  faces: {
    'sim-0-obverse': { face: 'obverse', pixel_size_um: 200, assets: 'faces/sim-0-obverse' },
    'sim-0-reverse': { face: 'reverse', pixel_size_um: 250 },
  },
  pixel_size_um: 300,
};
const faces = faceFrames(transforms, report);
const close = (a, b) => a.forEach((v, i) => expect(v).toBeCloseTo(b[i], 12));

describe('faceFrames', () => {
  it('reads each face, its folder, its face name and its pixel size', () => {
    expect(faces.map((f) => f.label)).toEqual(['sim-0-obverse', 'sim-0-reverse', 'sim-0-left']);
    expect(faces.map((f) => f.prefix)).toEqual(['faces/sim-0-obverse/', 'faces/sim-0-reverse/', 'faces/sim-0-left/']);
    expect(faces.map((f) => f.face)).toEqual(['obverse', 'reverse', null]);
    expect(faces.map((f) => f.pixelMm)).toEqual([0.2, 0.25, 0.3]); // the last: the report's own
  });

  it('leaves out a face whose transform is malformed, and reads nothing from nothing', () => {
    const bad = { scans: { a: { rotation: [[1, 0], [0, 1]], translation_mm: [0, 0, 0] }, b: { rotation: I, translation_mm: [0, NaN, 0] }, c: null } };
    expect(faceFrames(bad)).toEqual([]);
    expect(faceFrames(null)).toEqual([]);
  });
});

describe('frames', () => {
  it('turns the light into the face scan frame by the inverse rotation', () => {
    const reverse = faces[1];
    // A light from the tablet's -z side (toward the obverse camera) lies behind the reverse.
    close(tabletToScanDir(reverse, [0, 0, -1]), [0, 0, 1]);
    const l = lightDirection(30, 40);
    close(tabletToScanDir(reverse, scanToTabletDir(reverse, l)), l);
    close(tabletToScanDir(faces[2], [1, 0, 0]), [0, 0, 1]);
  });

  it('places a point of the face image grid in the tablet frame', () => {
    close(scanToTabletPoint(faces[1], [2, 3, 0]), [2, 37, 20]);
  });
});

describe('faceInView', () => {
  it('chooses the face whose own camera looked along the view', () => {
    expect(faceInView(faces, [0, 0, 1]).face.label).toBe('sim-0-obverse'); // looking along +z
    expect(faceInView(faces, [0, 0, -1]).face.label).toBe('sim-0-reverse');
    // The edge face's camera sat on the tablet's -x side: seen looking along +x.
    const edge = faceInView(faces, [1, 0.2, 0.1]);
    expect(edge.face.label).toBe('sim-0-left');
    expect(edge.cosine).toBeGreaterThan(0.9);
    expect(faceInView([], [0, 0, 1])).toBeNull();
    expect(() => faceInView(faces, [0, 0, 0])).toThrow(RangeError);
  });

  it('with the light turned into its frame, picks the photograph of that face under that light', () => {
    // The reverse scan photographed under a light from its own azimuth 0° (scan +y).
    const index = { photos: [0, 90, 180, 270].map((a) => ({ file: `p${a}.jpg`, azimuth_deg: a, light: lightDirection(a, 60) })) };
    const reverse = faceInView(faces, [0, 0, -1]).face;
    const world = scanToTabletDir(reverse, lightDirection(0, 60));
    expect(nearestPhoto(index, tabletToScanDir(reverse, world)).photo.azimuth_deg).toBe(0);
    // Without the rotation, the world light would name the opposite photograph: the turn matters.
    expect(nearestPhoto(index, world).photo.azimuth_deg).toBe(180);
  });
});

describe('the face a picked part names', () => {
  it("matches model.glb's label or a streamed tablet's folder name", async () => {
    const { faceOfPart } = await import('../../src/viewer/photoFaces.js');
    const faces = [
      { label: 'sim 0/obverse', prefix: 'faces/sim_0_obverse/' },
      { label: 'reverse', prefix: 'faces/reverse/' },
    ];
    expect(faceOfPart(faces, 'sim 0/obverse')).toBe(faces[0]);
    expect(faceOfPart(faces, 'sim_0_obverse')).toBe(faces[0]); // a tile's dh_face
    expect(faceOfPart(faces, 'reverse')).toBe(faces[1]);
    expect(faceOfPart(faces, 'left')).toBeNull();
    expect(faceOfPart(faces, null)).toBeNull();
  });
});
