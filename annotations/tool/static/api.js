// Talking to the local server: same origin only, the per-launch token on every write.

const TOKEN_KEY = "bench4d-token";

// The server prints the page address with "#token=..." at its end; a fragment never leaves the browser. Keep the
// token for this tab (reloads) and take it out of the address bar.
export function readToken() {
  const m = /(?:^#|&)token=([A-Za-z0-9_-]+)/.exec(window.location.hash);
  if (m) {
    sessionStorage.setItem(TOKEN_KEY, m[1]);
    history.replaceState(null, "", window.location.pathname + window.location.search);
    return m[1];
  }
  return sessionStorage.getItem(TOKEN_KEY);
}

export class HttpError extends Error {
  constructor(status, body) {
    super((body && body.error) || `HTTP ${status}`);
    this.status = status;
    this.body = body;
  }
}

export class Api {
  constructor(token) {
    this.token = token;
  }

  async get(path) {
    const res = await fetch(path, { cache: "no-store", credentials: "same-origin" });
    const body = await res.json().catch(() => null);
    if (!res.ok) throw new HttpError(res.status, body);
    return body;
  }

  async post(path, payload, { keepalive = false } = {}) {
    const res = await fetch(path, {
      method: "POST",
      credentials: "same-origin",
      keepalive,
      headers: { "Content-Type": "application/json", "X-Bench4d-Token": this.token || "" },
      body: JSON.stringify(payload),
    });
    const body = await res.json().catch(() => null);
    if (!res.ok) throw new HttpError(res.status, body);
    return body;
  }
}
