// The REST calls the viewer makes, with the server's rules: JSON bodies are sent as
// `application/json` (anything else is a 415), and changes carry `Authorization: Bearer` when
// the page was opened with `?token=` (servers with an admin token need it for sessions).

/** A refusal from the server, with its stable error code. */
export class ApiError extends Error {
  constructor(status, code, message) {
    super(`${status} ${code}: ${message}`);
    this.name = 'ApiError';
    this.status = status;
    this.code = code;
  }
}

export class Api {
  /** @param {string|null} token the admin token, if any */
  constructor(token) {
    this.token = token;
  }

  async request(method, path, body) {
    const headers = { accept: 'application/json' };
    if (body !== undefined) headers['content-type'] = 'application/json';
    if (this.token) headers.authorization = `Bearer ${this.token}`;
    let resp;
    try {
      resp = await fetch(path, {
        method,
        headers,
        body: body === undefined ? undefined : JSON.stringify(body),
      });
    } catch (e) {
      throw new ApiError(0, 'network', `${method} ${path}: ${e.message}`);
    }
    if (resp.status === 204) return null;
    let json = null;
    try {
      json = await resp.json();
    } catch {
      // A non-JSON body is reported below with the status alone.
    }
    if (!resp.ok) {
      const err = json && json.error;
      throw new ApiError(resp.status, err ? err.code : 'http', err ? err.message : `${method} ${path}`);
    }
    return json;
  }

  rig(id) {
    return this.request('GET', `/v1/rigs/${encodeURIComponent(id)}`);
  }

  mesh(id, lod) {
    return this.request('GET', `/v1/rigs/${encodeURIComponent(id)}/mesh?lod=${lod}`);
  }

  /** The rig's glTF materials, textures, samplers and images (always JSON). */
  materials(id) {
    return this.request('GET', `/v1/rigs/${encodeURIComponent(id)}/materials`);
  }

  /** The rig's expression layers: per material its layers and the URI of its texels. */
  layers(id) {
    return this.request('GET', `/v1/rigs/${encodeURIComponent(id)}/layers`);
  }

  createSession(req) {
    return this.request('POST', '/v1/sessions', req);
  }

  session(id) {
    return this.request('GET', `/v1/sessions/${encodeURIComponent(id)}`);
  }

  patchSession(id, patch) {
    return this.request('PATCH', `/v1/sessions/${encodeURIComponent(id)}`, patch);
  }
}

/** Decodes a JSON Blob (standard base64 of little-endian bytes) into a fresh ArrayBuffer. */
export function base64Bytes(s) {
  const bin = atob(s);
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out.buffer;
}
