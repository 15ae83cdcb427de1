/*
 * The API documentation pages: /docs (Swagger UI) and /redoc (ReDoc), both from the
 * vendored bundles under /static/vendor, so they work offline and under the service's
 * Content-Security-Policy (no inline script).  /openapi.json needs a key: the page uses
 * the one the dashboard keeps in this tab's sessionStorage, or asks for one.  Swagger UI
 * sends it with every "Try it out" request too, and shows it in its Authorize dialog.
 * A tab of its own (a new window) has no dashboard key: sessionStorage is per tab.
 */
"use strict";

const KEY_STORAGE = "loopwatch.apiKey"; // the dashboard's (app.js)

async function readSchema(key) {
  const response = await fetch("/openapi.json", { headers: { "X-API-Key": key } });
  if (!response.ok) {
    const body = await response.json().catch(() => ({}));
    throw new Error(`${response.status}: ${body.detail || response.statusText}`);
  }
  return response.json();
}

function show(schema, key) {
  const target = document.getElementById("docs");
  target.replaceChildren();
  if (document.body.dataset.viewer === "redoc") {
    // ReDoc's <style> elements carry this response's nonce (the page's policy allows
    // them by it); search runs in a blob: worker, which the policy does not allow
    const nonce = document.querySelector("meta[name=loopwatch-style-nonce]").content;
    window.Redoc.init(schema, { nonce, disableSearch: true }, target);
  } else {
    // The key fills Swagger UI's own authorization too (QA: its Authorize dialog asked
    // for the key the page already had): the padlocks show locked, copied curl commands
    // carry the header.
    const [scheme] = Object.entries((schema.components || {}).securitySchemes || {})
      .find(([, s]) => s.type === "apiKey" && s.in === "header" && s.name === "X-API-Key")
      || [null];
    const ui = window.SwaggerUIBundle({
      spec: schema,
      domNode: target,
      onComplete: () => { if (scheme) ui.preauthorizeApiKey(scheme, key); },
      requestInterceptor: (request) => {
        request.headers["X-API-Key"] = key;
        return request;
      },
    });
  }
}

async function start() {
  const form = document.getElementById("docs-key");
  const input = document.getElementById("docs-api-key");
  const error = document.getElementById("docs-error");
  const tryKey = async (key) => {
    show(await readSchema(key), key);
    sessionStorage.setItem(KEY_STORAGE, key);
    form.hidden = true;
  };
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    try {
      await tryKey(input.value.trim());
    } catch (err) {
      error.textContent = `The key was not accepted: ${err.message}`;
    }
  });
  const stored = sessionStorage.getItem(KEY_STORAGE);
  if (stored) {
    try {
      await tryKey(stored);
      return;
    } catch (err) {
      error.textContent = `The stored key was not accepted: ${err.message}`;
    }
  }
  form.hidden = false;
  input.focus();
}

start();
