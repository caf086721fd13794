/**
 * All HTTP to the library service (/api/v1, docs/architecture.md) goes through this module.
 * Errors become {@link ApiError} carrying the server's `detail`, `where` and `problems`.
 */

export const API_PREFIX = '/api/v1';

export class ApiError extends Error {
  /**
   * @param {number} status HTTP status (0: the network failed)
   * @param {string} detail the server's message
   * @param {{where?: string|null, problems?: {where: string, message: string}[]}} [extra]
   */
  constructor(status, detail, { where = null, problems = [] } = {}) {
    super(where ? `${detail} (${where})` : detail);
    this.name = 'ApiError';
    this.status = status;
    this.detail = detail;
    this.where = where;
    this.problems = problems;
  }
}

async function request(method, path, { query, json, body, headers = {}, signal } = {}) {
  let url = path.startsWith('/') ? path : `${API_PREFIX}/${path}`;
  if (query) {
    const q = new URLSearchParams();
    for (const [k, v] of Object.entries(query)) {
      if (v === undefined || v === null || v === '') continue;
      q.set(k, String(v));
    }
    const text = q.toString();
    if (text) url += `?${text}`;
  }
  const init = { method, headers: { Accept: 'application/json', ...headers }, credentials: 'same-origin', signal };
  if (json !== undefined) {
    init.headers['Content-Type'] = 'application/json';
    init.body = JSON.stringify(json);
  } else if (body !== undefined) {
    init.body = body;
  }
  let response;
  try {
    response = await fetch(url, init);
  } catch (err) {
    if (err.name === 'AbortError') throw err;
    throw new ApiError(0, `the library service cannot be reached (${err.message})`);
  }
  if (response.status === 204) return null;
  const type = response.headers.get('Content-Type') ?? '';
  const data = type.includes('json') ? await response.json().catch(() => null) : await response.text();
  if (!response.ok) {
    const detail =
      (data && typeof data === 'object' && (typeof data.detail === 'string' ? data.detail : null)) ||
      `${method} ${url} failed with HTTP ${response.status}`;
    throw new ApiError(response.status, detail, {
      where: data?.where ?? null,
      problems: Array.isArray(data?.problems) ? data.problems : [],
    });
  }
  return data;
}

const api = (path) => `${API_PREFIX}${path}`;

// --- auth -------------------------------------------------------------------------------------
export const login = (email, password) => request('POST', api('/auth/login'), { json: { email, password } });
export const logout = () => request('POST', api('/auth/logout'));
/** The signed-in user, or null for an anonymous reader (200 either way: no failed request logged). */
export const sessionUser = () => request('GET', api('/auth/session')).then((session) => session.user);

// --- tablets ----------------------------------------------------------------------------------
/**
 * Search the catalogue.
 * @param {{q?: string, period?: string, provenience?: string, genre?: string, collection?: string,
 *   language?: string, has_3d?: boolean, sort?: string, page?: number, page_size?: number}} params
 * @returns {Promise<{items: object[], total: number, page: number, page_size: number,
 *   facets: Record<string, {value: string|boolean|null, count: number}[]>}>}
 */
export const searchTablets = (params, { signal } = {}) =>
  request('GET', api('/tablets'), { query: { ...params, format: 'json' }, signal });
export const searchUrl = (params, format) => {
  const q = new URLSearchParams();
  for (const [k, v] of Object.entries({ ...params, format })) if (v !== undefined && v !== null && v !== '') q.set(k, v);
  return `${api('/tablets')}?${q}`;
};
export const getTablet = (id) => request('GET', api(`/tablets/${encodeURIComponent(id)}`));
export const createTablet = (fields) => request('POST', api('/tablets'), { json: fields });
export const tabletScans = (id) => request('GET', api(`/tablets/${encodeURIComponent(id)}/scans`));
export const tabletUrl = (id) => api(`/tablets/${encodeURIComponent(id)}`);
export const iiifManifestUrl = (id) => api(`/tablets/${encodeURIComponent(id)}/iiif/manifest.json`);

// --- scans, jobs, models ------------------------------------------------------------------------
export const getScan = (id) => request('GET', api(`/scans/${encodeURIComponent(id)}`));
export const getJob = (id, { signal } = {}) => request('GET', api(`/jobs/${encodeURIComponent(id)}`), { signal });
export const retryJob = (id) => request('POST', api(`/jobs/${encodeURIComponent(id)}/retry`));
/** The tablet-level models (registration of all scans: whole-tablet GLB, fatcross plates). */
export const tabletModels = (tabletId) => request('GET', api('/models'), { query: { tablet_id: tabletId } });
export const getModel = (id) => request('GET', api(`/models/${encodeURIComponent(id)}`));
/** Set a model's own licence URI and attribution (null clears one): staff of its institution. */
export const updateModel = (id, { licence, attribution }) =>
  request('PATCH', api(`/models/${encodeURIComponent(id)}`), { json: { licence, attribution } });
export const modelAssetUrl = (id, name) =>
  api(`/models/${encodeURIComponent(id)}/assets/${name.split('/').map(encodeURIComponent).join('/')}`);

// --- uploads ----------------------------------------------------------------------------------
export const createUpload = ({ tablet_id, filename, size_bytes }) =>
  request('POST', api('/uploads'), { json: { tablet_id, filename, size_bytes } });
export const getUpload = (id) => request('GET', api(`/uploads/${encodeURIComponent(id)}`));
export const putChunk = (id, offset, bytes, { signal } = {}) =>
  request('PUT', api(`/uploads/${encodeURIComponent(id)}/chunks`), {
    query: { offset },
    body: bytes,
    headers: { 'Content-Type': 'application/octet-stream' },
    signal,
  });
export const completeUpload = (id, sha256) =>
  request('POST', api(`/uploads/${encodeURIComponent(id)}/complete`), { json: { sha256 } });

/** Turn an asset URL from the API (absolute or relative to the API) into one fetch accepts. */
export function assetHref(url) {
  if (/^(https?:)?\/\//.test(url) || url.startsWith('/')) return url;
  return `${API_PREFIX}/${url}`;
}

// --- transliterations and annotations (W3C Web Annotations, docs/api.md "Annotations") ----------
export const getTransliteration = (tabletId) =>
  request('GET', api(`/tablets/${encodeURIComponent(tabletId)}/transliteration`));
/** The tablet's annotations of every model version (an AnnotationPage), `q`: search words. */
export const tabletAnnotations = (tabletId, q) =>
  request('GET', api(`/tablets/${encodeURIComponent(tabletId)}/annotations`), { query: { q } });
export const createAnnotation = (modelId, body) =>
  request('POST', api(`/models/${encodeURIComponent(modelId)}/annotations`), { json: body });
export const updateAnnotation = (id, changes) =>
  request('PATCH', api(`/annotations/${encodeURIComponent(id)}`), { json: changes });
export const deleteAnnotation = (id) => request('DELETE', api(`/annotations/${encodeURIComponent(id)}`));
