// /docs (Swagger UI) and /redoc (ReDoc), both from this server's own copies of the viewers.
//
// The page is the same for every request: nothing from the URL is written into it. The OpenAPI document is behind
// the server's token; this script fetches it with "Authorization: Bearer <token>", the token being the one the
// user gave, here (the form shown after a 401) or on the dashboard (the same origin's localStorage entry). The
// viewers get the document as a value, so they fetch nothing themselves; Swagger UI is pre-authorised with the
// same token for "Try it out", and its Authorize button changes it.
"use strict";

const TOKEN_KEY = "compabs.token";  // the dashboard's key: a token given on either page serves both
const viewer = document.body.dataset.viewer;
const uiEl = document.getElementById("ui");
const formEl = document.getElementById("token-form");
const tokenEl = document.getElementById("token");
const noticeEl = document.getElementById("docs-notice");

function token() {
  return localStorage.getItem(TOKEN_KEY) || "";
}

function notice(text) {
  noticeEl.textContent = text;
  noticeEl.hidden = !text;
}

async function fetchDocument() {
  const headers = new Headers({Accept: "application/json"});
  const t = token();
  if (t) headers.set("Authorization", "Bearer " + t);
  const response = await fetch("/openapi.json", {headers, cache: "no-store"});
  if (response.status === 401 || response.status === 403) {
    formEl.hidden = false;
    tokenEl.focus();
    notice(`${response.status}: ${t ? "the API token is not accepted" : "the API needs a token"}. ` +
      "Enter it above (the dashboard's token is used when it has one).");
    return null;
  }
  if (!response.ok) {
    notice(`Cannot load the API description: ${response.status} ${response.statusText}`);
    return null;
  }
  return response.json();
}

function renderSwagger(doc) {
  const ui = window.SwaggerUIBundle({
    spec: doc,
    domNode: uiEl,
    deepLinking: true,
    layout: "BaseLayout",
    presets: [window.SwaggerUIBundle.presets.apis],
    showExtensions: true,
    showCommonExtensions: true,
    validatorUrl: null,  // no calls to swagger.io
  });
  const t = token();
  if (t) ui.preauthorizeApiKey("HTTPBearer", t);
  window.compabsDocs = ui;
}

function renderRedoc(doc) {
  window.Redoc.init(doc, {hideDownloadButton: true}, uiEl);
}

async function load() {
  let doc;
  try {
    doc = await fetchDocument();
  } catch (e) {
    notice(`Cannot load the API description: ${e.message}`);
    return;
  }
  if (!doc) return;
  formEl.hidden = true;
  notice("");
  uiEl.replaceChildren();
  if (viewer === "redoc") renderRedoc(doc);
  else renderSwagger(doc);
}

formEl.addEventListener("submit", (ev) => {
  ev.preventDefault();
  const value = tokenEl.value.trim();
  if (value) localStorage.setItem(TOKEN_KEY, value);
  else localStorage.removeItem(TOKEN_KEY);
  load();
});
load();
