import { describe, expect, it } from 'vitest';
import { bibtexKey, citeBibtex, citeText, isoDate } from '../../src/viewer/cite.js';
import { profileToCsv } from '../../src/viewer/profile.js';

const about = {
  tablet: 'VAT 15245',
  pNumber: 'P000001',
  institution: 'Museum A',
  modelId: 31,
  modelVersion: 2,
  face: 'obverse',
  view: {
    mode: 'curvature',
    light: { azimuthDeg: 315, polarDeg: 60 },
    measure: { tool: 'distance', lengthMm: 12.3456 },
  },
  permalink: 'https://library.example.org/tablet.html?id=12#m=31&az=315',
  accessed: new Date('2026-11-27T23:30:00Z'),
  licence: 'https://creativecommons.org/licenses/by/4.0/',
  attribution: 'Courtesy of Museum A',
};

describe('cite this view', () => {
  it('names tablet, model version, view, permalink, access date and licence in the text', () => {
    const text = citeText(about);
    expect(text).toContain('Museum A. VAT 15245 (P000001), obverse, 3-D model version 2 (model 31)');
    expect(text).toContain('curvature shading, light azimuth 315°, elevation 30°, distance 12.35 mm');
    expect(text).toContain(`${about.permalink} (accessed 2026-11-27)`);
    expect(text).toContain('Courtesy of Museum A');
    expect(text).toContain('Licence: https://creativecommons.org/licenses/by/4.0/');
  });

  it('writes a BibTeX @misc entry with url, urldate and an escaped title', () => {
    const bib = citeBibtex({ ...about, tablet: 'BM 80_150 & co' });
    expect(bib.startsWith('@misc{P000001_m31v2,\n')).toBe(true);
    expect(bib).toContain('title = {BM 80\\_150 \\& co (P000001), obverse: 3-D model version 2}');
    expect(bib).toContain(`url = {${about.permalink}}`);
    expect(bib).toContain('urldate = {2026-11-27}');
    expect(bib).toContain('\\url{https://creativecommons.org/licenses/by/4.0/}');
    expect(bib.trim().endsWith('}')).toBe(true);
  });

  it('keys and dates are stable', () => {
    expect(bibtexKey({ tablet: 'K 3375', modelId: 4, modelVersion: 1 })).toBe('K3375_m4v1');
    expect(isoDate(new Date('2026-01-02T00:00:00Z'))).toBe('2026-01-02');
  });
});

describe('profile CSV header', () => {
  it('says what was measured before the rows, in comment lines', () => {
    const csv = profileToCsv(
      { distanceMm: [0, 0.5], heightUm: [12.345, Number.NaN] },
      { tablet: 'VAT 1', pNumber: 'P000002', modelId: 7, modelVersion: 3, start: [1, 2, 0.5], end: [4, 6, 0.25], licence: about.licence, permalink: 'x\ny' },
    );
    const lines = csv.trimEnd().split('\n');
    expect(lines).toContain('# tablet: VAT 1 (P000002)');
    expect(lines).toContain('# model: id 7, version 3');
    expect(lines).toContain('# start_mm: 1.0000, 2.0000, 0.5000');
    expect(lines).toContain('# end_mm: 4.0000, 6.0000, 0.2500');
    expect(lines).toContain(`# licence: ${about.licence}`);
    expect(lines).toContain('# permalink: x y'); // a newline cannot end the comment early
    expect(lines.filter((l) => !l.startsWith('#'))).toEqual(['distance_mm,height_um', '0.0000,12.35', '0.5000,']);
  });
});
