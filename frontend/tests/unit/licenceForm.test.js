import { describe, expect, it } from 'vitest';
import { ApiError } from '../../src/api.js';
import { canSetLicence, describeLicenceError, licenceBody } from '../../src/licenceForm.js';

const tablet = { id: 3, institution_id: 7 };

describe('canSetLicence', () => {
  it('lets admins and the holding institution staff set it, nobody else', () => {
    expect(canSetLicence({ role: 'admin', institution_id: null }, tablet)).toBe(true);
    expect(canSetLicence({ role: 'staff', institution_id: 7 }, tablet)).toBe(true);
    expect(canSetLicence({ role: 'staff', institution_id: 8 }, tablet)).toBe(false);
    expect(canSetLicence({ role: 'staff', institution_id: null }, { institution_id: null })).toBe(false);
    expect(canSetLicence({ role: 'reader', institution_id: 7 }, tablet)).toBe(false);
    expect(canSetLicence(null, tablet)).toBe(false);
    expect(canSetLicence({ role: 'admin' }, null)).toBe(false);
  });
});

describe('licenceBody', () => {
  it('trims the fields and clears a blank one', () => {
    expect(licenceBody('  https://creativecommons.org/licenses/by/4.0/ ', ' Museum ')).toEqual({
      licence: 'https://creativecommons.org/licenses/by/4.0/',
      attribution: 'Museum',
    });
    expect(licenceBody('', '   ')).toEqual({ licence: null, attribution: null });
    expect(licenceBody(undefined, null)).toEqual({ licence: null, attribution: null });
  });
});

describe('describeLicenceError', () => {
  it('names the field the API names, and says who may', () => {
    const invalid = new ApiError(422, 'invalid request', {
      where: 'body.licence',
      problems: [{ where: 'body.licence', message: 'not a Creative Commons or RightsStatements URI' }],
    });
    expect(describeLicenceError(invalid)).toBe('The licence was not saved: body.licence: not a Creative Commons or RightsStatements URI');
    expect(describeLicenceError(new ApiError(403, 'tablet 3: not editable'))).toBe('Not allowed: tablet 3: not editable');
    expect(describeLicenceError(new ApiError(401, 'sign in'))).toMatch(/^Sign in/);
    expect(describeLicenceError(new ApiError(0, 'the library service cannot be reached'))).toMatch(/cannot be reached/);
  });
});
