import { describe, expect, it } from 'vitest';
import {
  decodeViewState,
  defaultViewState,
  encodeViewState,
  SHADING_MODES,
} from '../../src/viewer/permalink.js';

function sampleState(i) {
  return {
    model: 10 + i,
    camera: {
      projection: i % 2 ? 'perspective' : 'orthographic',
      position: [12.5 + i, -30.25, -140.125 * (i + 1)],
      target: [30, 20.5, -1.75],
      up: [0, -1, 0],
      zoom: 1 + i / 4,
    },
    light: {
      azimuthDeg: (37 * i) % 360,
      polarDeg: 10 + 11 * i, // up to 175°: the light anywhere on the sphere
      intensity: 0.5 + i / 10,
      ambient: 0.25,
      gloss: (i % 10) / 10,
      follow: i % 2 === 1,
    },
    shading: {
      mode: SHADING_MODES[i % SHADING_MODES.length],
      curvatureScale: i % 3,
      exaggeration: 1 + i / 2,
      quality: [null, 'quality_residual.png', null, 'quality/walls.npy'][i % 4], // a map in its folder too
      trustLayer: ['sources', 'uncertainty', 'disagreement'][i % 3],
    },
    hidden: [[], ['reverse'], ['top', 'left edge, 2nd scan'], ['obverse & co', 'r=1#x']][i % 4],
    measure: i % 3 ? null : { tool: i % 2 ? 'profile' : 'distance', points: [[i, 2.5, -0.5], [20, 10 + i, 0.25]] },
    enhance: {
      normalUnsharp: (i % 4) * 0.5,
      lumaUnsharp: (i % 3) * 1.25,
      radiusPx: 4 + i,
      lens: i % 2 ? { mode: ['trust', 'clay', 'relief'][i % 3], x: 100 + i, y: 50.5, radius: 80 } : null,
    },
  };
}

describe('permalink state', () => {
  it('round-trips camera, light and shading for every shading mode', () => {
    for (let i = 0; i < 16; i++) {
      const state = sampleState(i);
      const { state: back, ignored } = decodeViewState(`#${encodeViewState(state)}`);
      expect(ignored).toEqual([]);
      expect(back).toEqual(state);
    }
  });

  it('keeps 7 significant digits (0.1 µm on a 100 mm tablet) and is stable once encoded', () => {
    const state = sampleState(3);
    state.camera.position = [1 / 3, 2 / 3, -123.456789];
    const once = encodeViewState(state);
    const back = decodeViewState(once).state;
    expect(back.camera.position[2]).toBeCloseTo(-123.456789, 4);
    expect(Math.abs(back.camera.position[0] - 1 / 3)).toBeLessThan(1e-7);
    expect(encodeViewState(back)).toBe(once);
  });

  it('names a lens it cannot use and keeps the rest', () => {
    const { state, ignored } = decodeViewState('#mode=clay&un=2&lz=wireframe&lx=1&ly=2&lr=30');
    expect(ignored).toEqual(['lens']);
    expect(state.enhance).toEqual({ normalUnsharp: 2, lumaUnsharp: 0, radiusPx: 8, lens: null });
    expect(decodeViewState('#un=99').ignored).toEqual(['un']);
    // A lens on a mode with maps of its own comes back.
    expect(decodeViewState('#lz=curvature&lx=1&ly=2&lr=30').state.enhance.lens).toEqual({ mode: 'curvature', x: 1, y: 2, radius: 30 });
  });

  it('gives the defaults for an empty fragment', () => {
    expect(decodeViewState('')).toEqual({ state: defaultViewState(), ignored: [] });
  });

  it('names what it cannot use and keeps the rest', () => {
    const { state, ignored } = decodeViewState('az=90&po=195&mode=psychedelic&li=2&pos=1,2&cam=o&lf=yes');
    expect(ignored.sort()).toEqual(['camera', 'lf', 'mode', 'po']);
    expect(state.light.follow).toBe(false);
    expect(state.light.azimuthDeg).toBe(90);
    expect(state.light.polarDeg).toBe(defaultViewState().light.polarDeg);
    expect(state.light.intensity).toBe(2);
    expect(state.shading.mode).toBe('natural');
    expect(state.camera).toBeNull();
  });

  it('wraps azimuths into [0, 360)', () => {
    expect(decodeViewState('az=-90').state.light.azimuthDeg).toBe(270);
    expect(decodeViewState('az=725').state.light.azimuthDeg).toBe(5);
  });

  it('records hidden faces one name per key, so any node name survives', () => {
    const state = defaultViewState();
    state.hidden = ['reverse', 'a,b', 'x=y&z', 'Ω face #2', '  spaced  '];
    const fragment = encodeViewState(state);
    expect(fragment.match(/(^|&)hide=/g)).toHaveLength(5);
    const { state: back, ignored } = decodeViewState(fragment);
    expect(ignored).toEqual([]);
    expect(back.hidden).toEqual(state.hidden);
    expect(encodeViewState(defaultViewState())).not.toMatch(/hide=/);
  });

  it('drops unusable hidden-face names, keeps the others and says so', () => {
    const long = 'x'.repeat(201);
    const { state, ignored } = decodeViewState(`hide=reverse&hide=&hide=%20&hide=a%0Ab&hide=${long}&hide=top&hide=reverse`);
    expect(state.hidden).toEqual(['reverse', 'top']);
    expect(ignored).toEqual(['hide']);
    const many = Array.from({ length: 150 }, (_, i) => `hide=f${i}`).join('&');
    const capped = decodeViewState(many);
    expect(capped.state.hidden).toHaveLength(100);
    expect(capped.ignored).toEqual(['hide']);
    expect(decodeViewState('hide=reverse&hide=reverse').ignored).toEqual([]);
  });
});

describe('measurements in permalinks', () => {
  it('round-trips a distance and a profile between two points in mm', () => {
    for (const tool of ['distance', 'profile']) {
      const state = { ...defaultViewState(), measure: { tool, points: [[1.25, 2.5, -0.125], [30.5, 12, 0.75]] } };
      const { state: back, ignored } = decodeViewState(encodeViewState(state));
      expect(ignored).toEqual([]);
      expect(back.measure).toEqual(state.measure);
    }
  });

  it('has no measurement by default and names a broken one', () => {
    expect(decodeViewState('az=10').state.measure).toBeNull();
    for (const bad of ['mt=x&ma=1,2,3&mb=4,5,6', 'mt=d&ma=1,2,3', 'mt=p&ma=1,2,3&mb=1,2,3', 'mt=d&ma=1,2&mb=4,5,6']) {
      const { state, ignored } = decodeViewState(bad);
      expect(state.measure).toBeNull();
      expect(ignored).toContain('measurement');
    }
  });
});

describe('the quality map in a link', () => {
  it('keeps a map named with its folder and refuses empty folders, spaces, long names', () => {
    const state = defaultViewState();
    state.shading.quality = 'quality/fringe_disagreement_um.npy';
    expect(decodeViewState(`#${encodeViewState(state)}`).state.shading.quality).toBe('quality/fringe_disagreement_um.npy');
    for (const bad of ['quality//x.npy', '/x.npy', 'a b', 'x'.repeat(101)]) {
      const { ignored } = decodeViewState(`#mode=quality&qm=${encodeURIComponent(bad)}`);
      expect(ignored).toContain('qm');
    }
  });
});
