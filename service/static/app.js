/* loopwatch dashboard: a single page over the REST API, no build step, no external code.
 *
 * Pages (hash routes): #/ plant overview, #/loop/ID, #/loop/ID/model-check, #/unit/ID,
 * #/ticket/ID (printable).
 * The API key is asked for once and kept in sessionStorage (per browser tab); a link
 * ending in #key=... signs in too, and the key is removed from the address bar at once;
 * #key=...&/loop/ID (or &/unit/ID, &/ticket/ID) then opens that page.
 * Plots are SVG rendered by the server (GET /api/v1/loops/ID/plots/KIND), fetched with
 * the key and placed inline, so they are part of the page's accessibility tree.
 * "Large text" (kept in localStorage) enlarges everything for a control-room wall screen.
 */
"use strict";

const KEY_STORAGE = "loopwatch.apiKey";
const LARGE_TEXT_STORAGE = "loopwatch.largeText";
// Pages refresh every 15 s; a kiosk page (or the browser test) may set
// window.LOOPWATCH_REFRESH_MS before this script runs to change that.
const REFRESH_MS = Number(window.LOOPWATCH_REFRESH_MS) || 15000;
const OPEN_TICKET_STATES = ["open", "acknowledged", "scheduled"];
const SHELVE_CHOICES = [[3600, "1 h"], [8 * 3600, "8 h"], [24 * 3600, "24 h"]];
const TREND_WINDOWS = [[900, "15 min"], [3600, "1 h"], [4 * 3600, "4 h"], [24 * 3600, "24 h"]];

const session = { me: null, timer: null, refresh: null, page: 0 };

/* ------------------------------------------------------------------ DOM helpers */

/** Build an element: h("a", {href: "#/", class: "x", onclick: f}, "text", child, ...). */
function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (name.startsWith("on")) el.addEventListener(name.slice(2), value);
    else if (name === "class") el.className = value;
    else el.setAttribute(name, value === true ? "" : String(value));
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    el.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return el;
}

function announce(message) {
  const status = document.getElementById("status");
  status.textContent = message;
}

function utc(seconds) {
  if (seconds === null || seconds === undefined) return "—";
  return new Date(seconds * 1000).toISOString().replace("T", " ").slice(0, 19) + " UTC";
}

function num(value, digits = 2) {
  if (value === null || value === undefined || Number.isNaN(value)) return "—";
  return Number(value).toFixed(digits);
}

function loopLink(id) {
  return h("a", { href: `#/loop/${encodeURIComponent(id)}` }, id);
}

function section(title, id, ...content) {
  return h("section", { class: "card", "aria-labelledby": id },
    h("h2", { id }, title), ...content);
}

function table(caption, headers, rows, emptyText) {
  if (rows.length === 0) return h("p", { class: "empty" }, emptyText);
  return h("table", {},
    h("caption", { class: "visually-hidden" }, caption),
    h("thead", {}, h("tr", {}, headers.map((x) => h("th", { scope: "col" }, x)))),
    h("tbody", {}, rows));
}

function pill(text, tone) {
  return h("span", { class: `pill ${tone || ""}` }, text);
}

function verdictPill(verdict, confidence) {
  if (!verdict) return pill("not analysed", "muted");
  const tone = verdict === "stiction" ? "bad" : verdict === "no_stiction" ? "good" : "muted";
  const words = verdict.replace("_", " ");
  return pill(confidence === null || confidence === undefined ? words
    : `${words} (${num(confidence, 2)})`, tone);
}

function healthCell(health) {
  if (health === null || health === undefined) return h("td", {}, pill("unknown", "muted"));
  const tone = health < 40 ? "bad" : health < 75 ? "warn" : "good";
  return h("td", { class: "health" },
    h("meter", { min: 0, max: 100, low: 40, high: 75, optimum: 100, value: health,
      "aria-label": `health ${num(health, 0)} of 100` }),
    " ", pill(num(health, 0), tone));
}

/* ------------------------------------------------------------------ API */

class ApiError extends Error {
  constructor(status, detail) {
    super(typeof detail === "string" ? detail : JSON.stringify(detail));
    this.status = status;
  }
}

async function request(path, options = {}) {
  // A page still loading when its user signed out asks nothing more (it would only be
  // refused), and a refusal counts only for the key it was sent with: a late 401 of a
  // page left before a new sign-in must not sign the new session out.
  const key = sessionStorage.getItem(KEY_STORAGE);
  if (!key) throw new ApiError(401, "signed out");
  const headers = { "X-API-Key": key };
  if (options.body !== undefined) headers["Content-Type"] = "application/json";
  const response = await fetch(path, {
    method: options.method || "GET", headers,
    body: options.body === undefined ? undefined : JSON.stringify(options.body),
  });
  const wait = Number(response.headers.get("Retry-After"));
  if (response.status === 429 && !options.retried && wait > 0 && wait <= 10) {
    // the key's rate, or its one expensive analysis at a time: wait as told, try once more
    await new Promise((resolve) => setTimeout(resolve, wait * 1000));
    return request(path, { ...options, retried: true });
  }
  if (!response.ok) {
    let detail = response.statusText;
    try { detail = (await response.json()).detail; } catch (_) { /* not JSON */ }
    if (response.status === 401 && !options.signingIn
        && sessionStorage.getItem(KEY_STORAGE) === key) {
      signOut(`Signed out: ${detail}`);
    }
    throw new ApiError(response.status, detail);
  }
  return response;
}

/** Expensive analyses (advice, model check, unit diagnosis) go one at a time from this
 * tab: the server runs one per key and answers a second with 429 (a model check asked
 * while the loop page's advice still ran). */
let analysisQueue = Promise.resolve();
function analysis(path, options) {
  const answer = analysisQueue.then(() => api(path, options));
  analysisQueue = answer.catch(() => undefined);
  return answer;
}

async function api(path, options) {
  return (await request(`/api/v1${path}`, options)).json();
}

/** GET that answers null on 404: for parts that may not exist (yet). */
/** An inline server-rendered SVG plot, or a "not available" note with the reason.
 * With a body, the plot is drawn from it (POST): the model check sends its overlay. */
async function plot(loopId, kind, params = {}, body = undefined) {
  const query = new URLSearchParams(params).toString();
  const url = `/api/v1/loops/${encodeURIComponent(loopId)}/plots/${kind}${query ? "?" + query : ""}`;
  const method = body === undefined ? "GET" : "POST";
  const figure = h("figure", { class: "plot", "data-plot": kind });
  try {
    const text = await (await request(url, { method, body })).text();
    const svg = new DOMParser().parseFromString(text, "image/svg+xml").documentElement;
    if (svg.nodeName !== "svg") throw new Error("the server sent no SVG");
    svg.removeAttribute("width");
    svg.removeAttribute("height");
    figure.append(document.importNode(svg, true));
    figure.append(h("figcaption", {},
      h("a", { href: "#", onclick: (event) => downloadPng(event, url, loopId, kind, method, body) },
        "Download PNG", h("span", { class: "visually-hidden" }, ` of the ${kind} plot`))));
  } catch (error) {
    figure.classList.add("unavailable");
    // The server's detail is the reason alone; the plot is named here.
    figure.append(h("p", {}, `${kind[0].toUpperCase()}${kind.slice(1).replace("-", " ")} plot `
      + `not available: ${error.message}`));
  }
  return figure;
}

/** Fetch a file with the session's key (a plain link would not send it) and save it. */
async function saveFile(url, filename, options = {}) {
  const blob = await (await request(url, options)).blob();
  const link = h("a", { href: URL.createObjectURL(blob), download: filename });
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 10000);
}

async function downloadPng(event, svgUrl, loopId, kind, method, body) {
  event.preventDefault();
  const url = svgUrl + (svgUrl.includes("?") ? "&" : "?") + "format=png";
  try {
    await saveFile(url, `${loopId}-${kind}.png`, { method, body });
  } catch (error) {
    announce(`PNG not available: ${error.message}`);
  }
}

/* ------------------------------------------------------------------ sign in */

function signOut(message) {
  sessionStorage.removeItem(KEY_STORAGE);
  session.me = null;
  stopRefresh();
  document.getElementById("session").hidden = true;
  renderSignIn(message || "");
}

function renderSignIn(message) {
  const main = document.getElementById("main");
  const error = h("p", { id: "sign-in-error", class: "error", role: "alert" }, message);
  const input = h("input", { id: "api-key", name: "api-key", type: "password", required: true,
    autocomplete: "current-password", "aria-describedby": "api-key-help sign-in-error" });
  const form = h("form", { class: "card sign-in", onsubmit: async (event) => {
    event.preventDefault();
    sessionStorage.setItem(KEY_STORAGE, input.value.trim());
    try {
      await signIn();
      route();
    } catch (err) {
      sessionStorage.removeItem(KEY_STORAGE);
      error.textContent = `The key was not accepted: ${err.message}`;
      input.focus();
    }
  } },
  h("h1", {}, "Sign in to loopwatch"),
  h("label", { for: "api-key" }, "API key"),
  input,
  h("p", { id: "api-key-help", class: "help" },
    "Ask your administrator for a key (viewer, operator or maintenance). It is kept in ",
    "this browser tab only and forgotten when the tab closes."),
  h("button", { type: "submit" }, "Sign in"),
  error);
  main.replaceChildren(form);
  input.focus();
}

async function signIn() {
  session.me = await api("/me", { signingIn: true });
  document.getElementById("who-am-i").textContent =
    `${session.me.name} (${session.me.role})`;
  document.getElementById("session").hidden = false;
  const units = await api("/units");
  const nav = document.getElementById("nav-units");
  nav.replaceChildren(h("li", {}, h("a", { href: "#/" }, "Plant overview")),
    ...units.data.map((u) => h("li", {},
      h("a", { href: `#/unit/${encodeURIComponent(u.id)}` }, u.name || u.id))));
}

function may(permission) {
  return Boolean(session.me && session.me.permissions.includes(permission));
}

/* ------------------------------------------------------------------ refresh */

function stopRefresh() {
  if (session.timer) clearInterval(session.timer);
  session.timer = null;
  session.refresh = null;
}

function startRefresh(refresh) {
  stopRefresh();
  session.refresh = refresh;
  session.timer = setInterval(async () => {
    // Never pull a control from under a keyboard user: skip while one has focus in main.
    const focused = document.activeElement;
    if (focused && focused.closest("main") && focused.matches("button, select, input")) return;
    try {
      await refresh();
      announce(`Updated ${utc(Date.now() / 1000)}`);
    } catch (error) {
      announce(`Update failed: ${error.message}`);
    }
  }, REFRESH_MS);
}

/* ------------------------------------------------------------------ alarms and tickets */

async function alarmAction(alarm, action, body, after) {
  try {
    const updated = await api(`/alarms/${alarm.id}/${action}`, { method: "POST", body });
    announce(`Alarm ${alarm.id} on ${alarm.loop_id}: ${updated.state.replace("_", " ")}`);
  } catch (error) {
    announce(`Alarm ${alarm.id}: ${action} refused: ${error.message}`);
  }
  await after();
  // Keep a keyboard user's place: focus the redrawn row's first control.
  const row = document.querySelector(`#main tr[data-alarm-id="${alarm.id}"]`);
  const target = row && (row.querySelector("button") || row.querySelector("a"));
  if (target) target.focus();
}

function alarmButtons(alarm, after) {
  if (!may("alarms")) return h("td", {}, "—");
  const controls = h("div", { class: "actions" });
  const cell = h("td", {}, controls);
  if (alarm.state === "unacknowledged" || alarm.state === "rtn_unack") {
    controls.append(h("button", { type: "button", "data-action": "acknowledge",
      onclick: () => alarmAction(alarm, "acknowledge", {}, after) },
    "Acknowledge", h("span", { class: "visually-hidden" }, ` alarm ${alarm.id}`)));
  }
  if (alarm.state === "shelved") {
    controls.append(h("button", { type: "button", "data-action": "unshelve",
      onclick: () => alarmAction(alarm, "unshelve", {}, after) },
    "Unshelve", h("span", { class: "visually-hidden" }, ` alarm ${alarm.id}`)));
  } else if (alarm.state !== "out_of_service") {
    const id = `shelve-${alarm.id}-${session.page}`;
    const choice = h("select", { id, "aria-label": `Shelve alarm ${alarm.id} for` },
      SHELVE_CHOICES.map(([seconds, label]) => h("option", { value: seconds }, label)));
    controls.append(choice, h("button", { type: "button", "data-action": "shelve",
      onclick: () => alarmAction(alarm, "shelve",
        { duration_s: Number(choice.value), note: "shelved from the dashboard" }, after) },
    "Shelve", h("span", { class: "visually-hidden" }, ` alarm ${alarm.id}`)));
  }
  return cell;
}

function alarmsTable(alarms, after) {
  const rows = alarms.map((a) => h("tr", { "data-alarm-id": a.id, "data-state": a.state },
    h("td", {}, loopLink(a.loop_id)),
    h("td", {}, a.kind.replace("_", " ")),
    h("td", {}, pill(a.priority, a.priority === "high" ? "bad" : "")),
    h("td", { class: "alarm-state" }, a.state.replace("_", " ")),
    h("td", {}, a.message),
    h("td", {}, utc(a.raised_at)),
    alarmButtons(a, after)));
  return table("Active alarms", ["Loop", "Kind", "Priority", "State", "Message", "Raised",
    "Actions"], rows, "No active alarms.");
}

function ticketsTable(tickets) {
  const rows = tickets.map((t) => h("tr", { "data-ticket-id": t.id },
    h("td", {}, h("a", { href: `#/ticket/${t.id}` }, `#${t.id}`)),
    h("td", {}, t.valve_asset),
    h("td", {}, loopLink(t.loop_id)),
    h("td", {}, t.state),
    h("td", {}, t.priority),
    h("td", {}, t.title),
    h("td", {}, utc(t.created_at))));
  return table("Open tickets", ["Ticket", "Valve", "Loop", "State", "Priority", "Title",
    "Opened"], rows, "No open tickets.");
}

async function openTickets(params = "") {
  const all = await api(`/tickets?limit=1000${params}`);
  return all.data.filter((t) => OPEN_TICKET_STATES.includes(t.state));
}

/* ------------------------------------------------------------------ plant overview */

function rankByHealth(loops) {
  // Bad actors first; loops not analysed yet last (the rule of /plant/bad-actors).
  return [...loops].sort((a, b) => (a.health === null) - (b.health === null)
    || (a.health ?? 0) - (b.health ?? 0) || a.id.localeCompare(b.id));
}

/** The loop's KPI-based bad-actor score over the week (KPI severity x importance x share
 * of bad runs, GET /plant/bad-actors), and why in words beside it. */
function scoreCell(badActor) {
  if (!badActor || badActor.runs === 0) return h("td", { "data-score": "" }, "—");
  return h("td", { "data-score": badActor.score, title: badActor.why },
    num(badActor.score, 0), h("div", { class: "sub" }, badActor.why));
}

function percent0(fraction) {
  return fraction === null || fraction === undefined ? "—" : `${num(100 * fraction, 0)} %`;
}

/** The KPI columns of the overview, from each loop's latest run (GET /plant/bad-actors):
 * key, header, value, text, explanation, and whether a larger value is worse. */
const KPI_COLUMNS = [
  ["osc", "Osc. index", (k) => k.oscillation_index, (v) => num(v, 2),
    "oscillation index: 0 none, 1 a strongly regular cycle", true],
  ["harris", "Harris index", (k) => k.harris && k.harris.ratio, (v) => num(v, 2),
    "minimum variance / mean square error: 1 at minimum-variance control, towards 0 worse; "
    + "below it, where its dead time came from", false],
  ["error", "Error SD (%)", (k) => k.error && k.error.std, (v) => num(v, 2),
    "standard deviation of SP - PV, % of span", true],
  ["travel", "Travel (%/day)", (k) => k.travel_per_day, (v) => num(v, 0),
    "valve travel beyond noise, % of span per day", true],
  ["reversals", "Reversals /day", (k) => k.reversals_per_day, (v) => num(v, 0),
    "direction changes of the valve per day", true],
  ["saturation", "OP saturated", (k) => k.saturation, percent0,
    "share of time OP sat at a limit", true],
  ["service", "Auto / cascade", (k) => k.service_factor && k.service_factor.normal, percent0,
    "service factor: share of time in normal mode (needs a mode tag)", false],
];

/** Where one run's Harris index took its dead time from, in words: "Dead time:
 * configured", "Dead time: identified from set-point steps (3 samples, 2 s)", or "Dead
 * time: unknown: ..." with the reason; null for runs stored before the KPIs said so. */
function deadTimeNote(k) {
  if (!k || !k.dead_time_note) return null;
  const d = k.dead_time_samples === null || k.dead_time_samples === undefined ? ""
    : ` (${k.dead_time_samples} samples, ${num(k.dead_time_s, 3)} s)`;
  return `Dead time: ${k.dead_time_note}${d}`;
}

/** The same in a few words, under the overview's Harris index: the source of the run's
 * KPIs (configured, identified, unknown) and, when identified, from what (the note of
 * analytics.kpi.identify_dead_time); null for runs stored before the KPIs said so. */
function deadTimeSource(k) {
  if (!k || !k.dead_time_source) return null;
  if (k.dead_time_source !== "identified") return `dead time ${k.dead_time_source}`;
  const note = k.dead_time_note || "";
  if (note.startsWith("identified from set-point")) return "dead time from SP steps";
  if (note.startsWith("identified from the operator's OP moves")) {
    return "dead time from manual OP moves";
  }
  return "dead time identified";
}

/** An overview cell of one KPI column; the Harris index says where its dead time came
 * from below the figure, and in full (as the loop page does) in its tooltip. */
function kpiCell(key, kpis, value, text) {
  const v = kpis ? value(kpis) : null;
  const source = key === "harris" ? deadTimeSource(kpis) : null;
  if (!source) return h("td", { "data-kpi": key, "data-value": v ?? "" }, text(v));
  return h("td", { "data-kpi": key, "data-value": v ?? "",
    title: deadTimeNote(kpis) || source },
  text(v), h("div", { class: "sub", "data-dead-time": kpis.dead_time_source }, source));
}

/** Sortable columns of the overview besides the KPIs: key -> [value, larger is worse]. */
const OVERVIEW_SORTS = {
  health: [(l) => l.health, false],
  score: [(l, b) => b && b.runs ? b.score : null, true],
  ...Object.fromEntries(KPI_COLUMNS.map(([key, , value, , , worse]) =>
    [key, [(l, b) => (b && b.kpis ? value(b.kpis) ?? null : null), worse]])),
};

/** Loops sorted by one overview column, worst first (dir 1) or best first (dir -1); loops
 * without the figure last either way, then by health. */
function sortLoops(loops, scores, key, dir) {
  const [value, worse] = OVERVIEW_SORTS[key];
  const ranked = rankByHealth(loops);
  const order = new Map(ranked.map((l, i) => [l.id, i]));
  return ranked.sort((a, b) => {
    const x = value(a, scores.get(a.id));
    const y = value(b, scores.get(b.id));
    if ((x === null || x === undefined) !== (y === null || y === undefined)) {
      return (x === null || x === undefined) ? 1 : -1;
    }
    if (x === null || x === undefined || x === y) return order.get(a.id) - order.get(b.id);
    return (worse ? y - x : x - y) * dir;
  });
}

async function downloadReport(format) {
  try {
    await saveFile(`/api/v1/reports/bad-actors?period=7d&format=${format}&limit=50`,
      `bad-actors-7d.${format}`);
    announce(`Bad-actor report (${format.toUpperCase()}) downloaded.`);
  } catch (error) {
    announce(`Report not available: ${error.message}`);
  }
}

function oscillationText(loop) {
  if (loop.oscillating === null || loop.oscillating === undefined) return "—";
  return loop.oscillating ? `yes, ${num(loop.period_s, 0)} s` : "no";
}

async function renderOverview(params) {
  const main = document.getElementById("main");
  const units = await api("/units");
  const unitFilter = h("select", { id: "unit-filter", name: "unit" },
    h("option", { value: "" }, "All units"),
    units.data.map((u) => h("option", { value: u.id, selected: params.get("unit") === u.id },
      u.name || u.id)));
  const stateFilter = h("select", { id: "state-filter", name: "state" },
    [["", "All states"], ["oscillating", "Oscillating"], ["stiction", "Sticky valve"],
      ["healthy", "Not oscillating"], ["unknown", "Not analysed"]].map(([value, label]) =>
      h("option", { value, selected: params.get("state") === value }, label)));
  const applyFilters = () => {
    const query = new URLSearchParams();
    if (unitFilter.value) query.set("unit", unitFilter.value);
    if (stateFilter.value) query.set("state", stateFilter.value);
    location.hash = `#/?${query}`;
  };
  unitFilter.addEventListener("change", applyFilters);
  stateFilter.addEventListener("change", applyFilters);

  const loopsBox = h("div", { id: "loops" });
  const sort = { key: "health", dir: 1 };  // worst health first, the ranking of the API
  const alarmsBox = h("div", { id: "alarms" });
  const ticketsBox = h("div", { id: "tickets" });
  main.replaceChildren(
    h("h1", {}, "Plant overview"),
    h("form", { class: "filters", "aria-label": "Filter loops", onsubmit: (e) => e.preventDefault() },
      h("label", { for: "unit-filter" }, "Unit"), unitFilter,
      params.get("unit") ? h("a", { href: `#/unit/${encodeURIComponent(params.get("unit"))}` },
        "Unit page: the loops side by side and the sticky valves") : null,
      h("label", { for: "state-filter" }, "State"), stateFilter),
    section("Loops ranked by health (bad actors first)", "loops-title",
      h("p", { class: "inline-form" }, "Bad-actor report of the last 7 days, for the weekly "
        + "meeting: ",
      h("button", { type: "button", id: "report-pdf", onclick: () => downloadReport("pdf") },
        "Download PDF"), " ",
      h("button", { type: "button", id: "report-csv", onclick: () => downloadReport("csv") },
        "Download CSV")),
      loopsBox),
    section("Active alarms", "alarms-title", alarmsBox),
    section("Open tickets", "tickets-title", ticketsBox));

  const refresh = async () => {
    const query = new URLSearchParams({ limit: 1000 });
    if (params.get("unit")) query.set("unit", params.get("unit"));
    if (params.get("state")) query.set("state", params.get("state"));
    const alarmQuery = params.get("unit") ? `?unit=${encodeURIComponent(params.get("unit"))}` : "";
    const [loops, alarms, tickets, badActors] = await Promise.all([
      api(`/loops?${query}`), api(`/alarms${alarmQuery}`), openTickets(),
      api("/plant/bad-actors?limit=1000&period=7d")]);
    const unitLoops = new Set(loops.data.map((l) => l.id));
    // The KPI-based bad-actor score over the week (GET /plant/bad-actors), with its why,
    // and the latest run's KPIs.
    const scores = new Map(badActors.data.map((b) => [b.id, b]));
    const drawLoops = () => {
      const sorted = sortLoops(loops.data, scores, sort.key, sort.dir);
      const rows = sorted.map((l, i) => {
        const kpis = (scores.get(l.id) || {}).kpis || null;
        return h("tr", { "data-loop-id": l.id },
          h("td", {}, i + 1),
          h("th", { scope: "row" }, loopLink(l.id), h("div", { class: "sub" }, l.name)),
          h("td", {}, l.unit ? h("a", { href: `#/unit/${encodeURIComponent(l.unit)}` }, l.unit)
            : "—"),
          healthCell(l.health),
          // the diagnosis first, then the week's score and the KPIs (they scroll on a
          // narrow screen)
          h("td", {}, oscillationText(l)),
          h("td", {}, verdictPill(l.verdict, l.confidence)),
          h("td", {}, l.S === null ? "—" : `${num(l.S)}\u00a0/\u00a0${num(l.J)}`),
          h("td", {}, l.active_alarms),
          scoreCell(scores.get(l.id)),
          KPI_COLUMNS.map(([key, , value, text]) => kpiCell(key, kpis, value, text)));
      });
      const sortable = (key, label, title) => h("th", { scope: "col", title,
        "aria-sort": sort.key !== key ? "none" : (sort.dir === 1) === OVERVIEW_SORTS[key][1]
          ? "descending" : "ascending" },
      h("button", { type: "button", class: "sort", "data-sort": key, onclick: () => {
        sort.dir = sort.key === key ? -sort.dir : 1;
        sort.key = key;
        drawLoops();
      } }, label));
      const plain = (label) => h("th", { scope: "col" }, label);
      loopsBox.replaceChildren(rows.length === 0
        ? h("p", { class: "empty" }, "No loops match the filters.")
        : h("div", { class: "table-scroll" }, h("table", { id: "loops-table" },
          h("caption", { class: "visually-hidden" },
            "Loops with their latest KPIs; the column headers sort (worst first, again: "
            + "best first)"),
          h("thead", {}, h("tr", {}, plain("Rank"), plain("Loop"), plain("Unit"),
            sortable("health", "Health"), plain("Oscillation"), plain("Valve verdict"),
            plain("S / J (%)"), plain("Alarms"), sortable("score", "Bad-actor score (7 d)"),
            KPI_COLUMNS.map(([key, label, , , title]) => sortable(key, label, title)))),
          h("tbody", {}, rows))));
    };
    drawLoops();
    alarmsBox.replaceChildren(alarmsTable(alarms.data, refresh));
    ticketsBox.replaceChildren(ticketsTable(params.get("unit")
      ? tickets.filter((t) => unitLoops.has(t.loop_id)) : tickets));
  };
  await refresh();
  startRefresh(refresh);
}

/* ------------------------------------------------------------------ loop page */

const KPI_PERIODS = [[86400, "1 day"], [7 * 86400, "1 week"], [30 * 86400, "30 days"],
  [91 * 86400, "13 weeks"]];

/** The KPIs the loop page draws over time: key, header, value of one run's KPIs (or
 * health). */
const KPI_TRENDS = [
  ["health", "Health (0..100)", (p) => p.health],
  ...KPI_COLUMNS.map(([key, label, value]) =>
    [key, label, (p) => (p.kpis ? value(p.kpis) : null)]),
];

/** Where the latest run's Harris index took its dead time from, in words (deadTimeNote;
 * null for runs stored before the KPIs said so). */
function deadTimeText(history) {
  const latest = [...history.data].reverse().find((p) => p.kpis && p.kpis.dead_time_note);
  return latest ? deadTimeNote(latest.kpis) : null;
}

const SVG_NS = "http://www.w3.org/2000/svg";

function svg(tag, attrs, ...children) {
  const el = document.createElementNS(SVG_NS, tag);
  for (const [name, value] of Object.entries(attrs || {})) el.setAttribute(name, String(value));
  for (const child of children) {
    el.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return el;
}

/** One KPI over the runs as a small line chart (runs without the figure left out). */
function kpiChart(label, points, since, until) {
  const w = 280, hgt = 90, pad = 4;
  const data = points.filter(([, v]) => v !== null && v !== undefined && Number.isFinite(v));
  const figure = h("figure", { class: "kpi-chart", "data-kpi-trend": label });
  const caption = h("figcaption", {}, label);
  if (data.length === 0) {
    figure.append(caption, h("p", { class: "empty" }, "not computed in this period"));
    return figure;
  }
  const values = data.map(([, v]) => v);
  const low = Math.min(...values), high = Math.max(...values);
  const span = high - low || 1, tspan = until - since || 1;
  const xy = data.map(([t, v]) => [pad + (w - 2 * pad) * (t - since) / tspan,
    hgt - pad - (hgt - 2 * pad) * (v - low) / span]);
  const last = values[values.length - 1];
  caption.append(h("span", { class: "sub" },
    ` latest ${num(last, 2)}, range ${num(low, 2)} .. ${num(high, 2)}`));
  figure.append(caption, svg("svg", { viewBox: `0 0 ${w} ${hgt}`, width: w, height: hgt,
    role: "img", "aria-label": `${label} over the period: ${data.length} runs, latest `
      + `${num(last, 2)}, lowest ${num(low, 2)}, highest ${num(high, 2)}` },
  svg("rect", { x: 0.5, y: 0.5, width: w - 1, height: hgt - 1, class: "frame" }),
  data.length === 1 ? svg("circle", { cx: xy[0][0], cy: xy[0][1], r: 2.5, class: "line" })
    : svg("polyline", { points: xy.map((p) => p.join(",")).join(" "), class: "line" })));
  return figure;
}

/** The KPI history of a loop (GET /loops/{id}/kpis) over days to weeks. */
async function kpiTrendSection(path, end) {
  const box = h("div", { class: "kpi-grid", id: "kpi-trend" });
  const choice = h("select", { id: "kpi-period" }, KPI_PERIODS.map(([seconds, label]) =>
    h("option", { value: seconds, selected: seconds === 7 * 86400 }, label)));
  const show = async () => {
    const until = end ?? Date.now() / 1000;
    const since = until - Number(choice.value);
    const history = await api(`${path}/kpis?since=${since}&until=${until}&limit=500`);
    const note = history.total > history.count
      ? ` (every ${Math.ceil(history.total / history.count)}th of ${history.total} runs)` : "";
    box.replaceChildren(h("p", { class: "help" },
      `${history.count} analysis runs${note}, ${utc(since)} to ${utc(until)}.`),
    ...KPI_TRENDS.map(([key, label, value]) => {
      const chart = kpiChart(label, history.data.map((p) => [p.started_at, value(p)]),
        since, until);
      const deadTime = key === "harris" ? deadTimeText(history) : null;
      if (deadTime) chart.append(h("p", { class: "sub", "data-dead-time": "" }, deadTime));
      return chart;
    }));
  };
  choice.addEventListener("change", show);
  await show();
  return section("KPI trend", "kpi-trend-title",
    h("div", { class: "inline-form" }, h("label", { for: "kpi-period" },
      "Period ending at the latest analysis"), choice), box);
}

function definitionList(pairs) {
  return h("dl", { class: "facts" }, pairs.flatMap(([term, value]) =>
    [h("dt", {}, term), h("dd", {}, value)]));
}

function methodsTable(diagnosis) {
  const methods = Object.entries(((diagnosis || {}).stiction || {}).methods || {});
  const rows = methods.map(([name, m]) => h("tr", { "data-method": name },
    h("th", { scope: "row" }, name.replace("_", " ")),
    h("td", {}, verdictPill(m.decision)),
    h("td", {}, num(m.index, 3)),
    h("td", {}, num(m.confidence, 2)),
    h("td", {}, m.note)));
  return table("Stiction detection methods", ["Method", "Decision", "Index", "Confidence",
    "Evidence"], rows, "No detection method ran (no oscillation, or the data were unusable).");
}

/** The stick-jump episodes (GET /loops/ID/health "episodes", or a ticket's evidence):
 * UNIX times, OP travel while the valve held and the PV jump, % of span. */
function episodesTable(episodes, emptyText) {
  return table("Stick-jump episodes", ["Hold from", "Jump at", "PV settled", "OP travel (%)",
    "PV jump (%)"], (episodes || []).map((e) => h("tr", { "data-episode": "" },
    h("td", {}, utc(e.start)), h("td", {}, utc(e.jump)), h("td", {}, utc(e.end)),
    h("td", {}, num(e.op_travel)), h("td", {}, num(e.pv_jump)))), emptyText);
}

function estimateFacts(diagnosis) {
  const q = (diagnosis || {}).quantification;
  const apparent = (diagnosis || {}).apparent_stiction;
  const band = ((diagnosis || {}).stiction || {}).episode_stick_band;
  if (!q && !apparent && (band === null || band === undefined)) return h("p", { class: "empty" },
    "No stiction estimate: S and J are estimated for sticky valves only.");
  const pairs = [];
  const size = (diagnosis || {}).valve;
  if (size && size.S_interval) {
    // the valve's size combined over the windows of its streak (issue 19), nominal 95 %
    // intervals (on simulated valves they hold the true size in about 5 cases of 6)
    const windows = size.size_windows.length;
    pairs.push([windows === 1 ? "Valve size, from 1 window" : `Valve size, ${windows} windows `
      + "combined",
      `S ${num(size.S)} % (${num(size.S_interval[0])} to ${num(size.S_interval[1])}), `
      + `J ${num(size.J)} % (${num(size.J_interval[0])} to ${num(size.J_interval[1])})`]);
    if (size.J_note) pairs.push(["J of the valve size", size.J_note]);
  }
  if (q) {
    // This window's own estimate: beside the combined size it is a second S and J, said so.
    const own = size && size.S_interval ? ", this window" : "";
    pairs.push([`S (stick band + deadband)${own}`, `${num(q.S)} % of span`],
      [`J (slip jump)${own}`, `${num(q.J)} % of span`],
      ["fs, fd (He's model)", `${num(q.fs)}, ${num(q.fd)} %`],
      ["Fit R² (Hammerstein)", num(q.fit_r2, 3)],
      ["Valve model", q.valve_model],
      ["Process model", `K ${num(q.process.K, 3)}, τ ${num(q.process.tau, 1)} s, θ `
        + `${num(q.process.theta, 1)} s${q.process.integrating ? ", integrating" : ""}`],
      ["Process gain", q.gain_given ? `given: ${q.gain_source || "plant file"}`
        : `fitted${q.J_product_only ? ": J known only through K·J " + num(q.KJ, 3) : ""}`],
      ["Trustworthy", q.trustworthy ? "yes" : `no: ${q.issues.join("; ")}`]);
  }
  if (apparent) {
    pairs.push(["Apparent stiction (ellipse)", `${num(apparent.apparent_stiction)} % of span `
      + `(width ratio ${num(apparent.width_ratio)})`]);
  }
  const sized = ((diagnosis || {}).stiction || {}).episode_size;
  if (sized && sized.S !== null && sized.S !== undefined) {
    // OP's travel from its turn to the slip measures S (analytics.stiction.episode_size)
    pairs.push(["S from the episodes", `${num(sized.S)} % of span (OP's travel from its turn `
      + `to the slip, median of ${sized.reversals} after a reversal)`]);
    if (sized.note) pairs.push(["Episodes and Hammerstein", sized.note]);
  }
  if (band !== null && band !== undefined) {
    pairs.push(["OP travel while PV held", `${num(band)} % of span (a lower bound of S: the `
      + "hold shows only once PV has settled)"]);
  }
  return definitionList(pairs);
}

function cycleText(cycle) {
  if (!cycle) return "—";
  if (!cycle.oscillating) return "no cycle";
  const amplitude = (cycle.amplitudes || []).filter((a) => a !== null).map((a) => num(a));
  return `cycle ${num(cycle.period_s, 0)} s, OP amplitude ${amplitude.join(", ") || "—"} %`;
}

function tuningText(tunings) {
  return (tunings || []).map((t) => `Kc ${num(t.Kc, 3)}, Ti ${num(t.Ti, 1)} s`).join("; ");
}

function detuningResult(advice) {
  // Detuning of a loop that cycles with a healthy valve: Kc lowered for a gain margin.
  const rows = advice.recommendations.map((r) => h("tr", { "data-advice": "recommended" },
    h("td", {}, tuningText(r.tunings)), h("td", {}, r.source),
    h("td", {}, `gain margin ${r.gain_margin.toFixed(1)}`)));
  return h("div", {},
    definitionList([["Current tuning", tuningText(advice.current)],
      ["Cycle (ultimate period)", `${advice.ultimate_period_s.toFixed(1)} s`]]),
    table("Detuning", ["Tuning", "From", "Predicted"], rows, "No detuning."),
    ...advice.notes.map((note) => h("p", { class: "note" }, note)));
}

function noisyTravelText(rate, current) {
  // Valve travel with the measured PV noise, against the current tuning's (null: not known).
  if (rate === null || rate === undefined || !current) return "not checked";
  return `valve travel ${(rate / current).toFixed(2)} x the current tuning's`;
}

function loadErrorText(ratio) {
  // The error a load step leaves under a retune, against the current tuning's.
  if (ratio === null || ratio === undefined) return "not known";
  return `${ratio.toFixed(2)} x the current tuning's`;
}

function adviceResult(advice) {
  // Tuning advice (GET /loops/{id}/advice): every candidate was predicted with the describing
  // function and simulated, then simulated again with the measured PV noise; only the ones
  // both simulations confirm are recommended.
  if (advice.kind === "detuning") return detuningResult(advice);
  const noisyNow = advice.current_travel_rate_with_noise;
  const rows = [...advice.recommendations.map((r) => [r, "recommended"]),
    ...advice.rejected.map((r) => [r, "not recommended"])].map(([r, kind]) =>
    h("tr", { "data-advice": kind },
      h("td", {}, tuningText(r.tunings)), h("td", {}, r.source),
      h("td", {}, cycleText(r.predicted)), h("td", {}, cycleText(r.simulated)),
      h("td", { "data-column": "with-noise" },
        noisyTravelText(r.travel_rate_with_noise, noisyNow)),
      h("td", { "data-column": "load-error" }, loadErrorText(r.load_error_ratio)),
      h("td", {}, `${kind}: ${r.outcome}`)));
  return h("div", {},
    definitionList([
      ["Current tuning", tuningText(advice.current)],
      ["Current, predicted", cycleText(advice.current_predicted)],
      ["Current, simulated", cycleText(advice.current_simulated)],
      ["Against the measured cycle", advice.measured_cycle.explanation],
    ]),
    table("Candidate tunings", ["Tuning", "From", "Predicted", "Simulated",
      "With the PV noise", "Error after a load", "Verdict"], rows, "No candidate tuning."),
    ...(advice.notes || []).map((note) => h("p", { class: "note" }, note)));
}

/** Why the Nyquist plot and the tuning advice cannot be had for this diagnosis, known
 * without asking: the page redraws at every analysis, and a healthy loop's page would
 * otherwise log a 404 and a 409 on the server and in the console every time. */
const NO_NYQUIST = "the latest analysis has no stiction estimate (S, J) with an identified "
  + "process model";
const NO_ADVICE = "Advice not available: the loop does not cycle and its valve is not sticky; "
  + "there is nothing to retune";

function nyquistUnavailable(diagnosis) {
  const q = diagnosis ? diagnosis.quantification : undefined;
  return diagnosis && (!q || q.S === null || q.S === undefined || !q.process) ? NO_NYQUIST
    : null;
}

function adviceUnavailable(diagnosis) {
  if (!diagnosis || !diagnosis.oscillation || diagnosis.oscillation.detected) return null;
  const valve = diagnosis.valve || diagnosis.stiction;
  return valve && valve.verdict !== "stiction" ? NO_ADVICE : null;
}

function unavailablePlot(kind, reason) {
  return h("figure", { class: "plot unavailable", "data-plot": kind },
    h("p", {}, `${kind[0].toUpperCase()}${kind.slice(1)} plot not available: ${reason}`));
}

function adviceSection(path, unavailable = null) {
  // The advice simulates the loop model (seconds on a busy server): the page is shown at
  // once and the advice fills its box when it arrives.
  const box = h("div", { "data-advice-box": path });
  if (unavailable) {
    box.append(h("p", { class: "unavailable" }, unavailable));
    return section("Tuning advice", "advice-title", box);
  }
  box.setAttribute("aria-busy", "true");
  box.append(h("p", { class: "unavailable", role: "status" },
    "Working out the advice: the loop model is simulated at each tuning…"));
  analysis(path).then((advice) => box.replaceChildren(adviceResult(advice))).catch((error) => {
    // 409: the loop has no estimate or no controller yet; the answer says which
    box.replaceChildren(h("p", { class: "unavailable" }, error instanceof ApiError
      && error.status === 409 ? error.message : `Tuning advice: not available (${error.message}).`));
  }).finally(() => box.removeAttribute("aria-busy"));
  return section("Tuning advice", "advice-title", box);
}

async function renderLoop(loopId) {
  const main = document.getElementById("main");
  const path = `/loops/${encodeURIComponent(loopId)}`;
  const [loop, health] = await Promise.all([api(path), api(`${path}/health`)]);
  const diagnosis = health.diagnosis;
  const latest = health.latest;
  const windowEnd = latest ? latest.window_end : null;

  const trendBox = h("div", { class: "plot-box" });
  const valuesBox = h("div", {});
  const windowChoice = h("select", { id: "trend-window" },
    TREND_WINDOWS.map(([seconds, label]) => h("option", { value: seconds,
      selected: seconds === 3600 }, label)));
  const showTrend = async () => {
    const params = {};
    if (windowEnd !== null) {
      params.end = windowEnd;
      params.start = windowEnd - Number(windowChoice.value);
    }
    // The latest values: the last five minutes of the window, not downsampled.
    const latestQuery = windowEnd === null ? "" : `?start=${windowEnd - 300}&end=${windowEnd}`;
    const [figure, data] = await Promise.all([plot(loopId, "trend", params),
      api(`${path}/data${latestQuery}`)]);
    trendBox.replaceChildren(figure);
    valuesBox.replaceChildren(table("Latest values", ["Signal", "Tag",
      "Latest value", "At"], data.series.map((s) => {
      const last = s.t.length - 1;
      return h("tr", {}, h("th", { scope: "row" }, s.signal.toUpperCase()), h("td", {}, s.tag),
        h("td", {}, last < 0 ? "—" : num(s.value[last], 2)), h("td", {}, last < 0 ? "—"
          : utc(s.t[last])));
    }), "No samples in the last five minutes of the window."));
  };
  windowChoice.addEventListener("change", showTrend);

  const quality = diagnosis ? diagnosis.quality.issues : [];
  const alarmsBox = h("div", {});
  const ticketsBox = h("div", {});
  // The final verdict on the valve (a unit's diagnosis may overrule the loop's own).
  const stiction = diagnosis ? diagnosis.valve || diagnosis.stiction : null;
  const oscillation = diagnosis ? diagnosis.oscillation : null;
  main.replaceChildren(
    h("p", { class: "crumbs" }, h("a", { href: "#/" }, "Plant overview"),
      loop.unit ? [" › ", h("a", { href: `#/unit/${encodeURIComponent(loop.unit)}` }, loop.unit)]
        : null),
    h("h1", {}, `${loop.id} `, h("span", { class: "sub" }, loop.name)),
    section("Diagnosis", "diagnosis-title", definitionList([
      ["Health", health.health === null ? "unknown" : `${num(health.health, 0)} of 100`],
      ["Oscillation", oscillation ? (oscillation.detected ? `yes, period `
        + `${num(oscillation.period_s, 0)} s, regularity ${num(oscillation.regularity, 1)}`
        : "no regular oscillation") : "not analysed"],
      ["Valve verdict", verdictPill(stiction && stiction.verdict, stiction && stiction.confidence)],
      ["Stiction pattern", health.stiction_pattern || "—"],
      ["Why", stiction ? stiction.reason : "—"],
      ...(diagnosis && diagnosis.manual ? [["Manual mode", diagnosis.manual.note]] : []),
      ...(stiction && stiction.decided_by === "unit" ? [["Decided by", `unit ${stiction.unit_id}'s `
        + `diagnosis; this loop's own analysis: ${diagnosis.stiction.verdict.replace("_", " ")}, `
        + "kept below as evidence"]] : []),
      ["Analysed", latest ? `${utc(latest.started_at)} (window ${utc(latest.window_start)} to `
        + `${utc(latest.window_end)})` : "not yet"],
      ["Valve", loop.valve_asset || "—"],
      ["Data quality", quality.length ? quality.map((i) => `${i.severity}: ${i.message}`)
        .join("; ") : "no issues"]])),
    section("Trend", "trend-title",
      h("div", { class: "inline-form" }, h("label", { for: "trend-window" },
        "Window ending at the latest analysis"), windowChoice),
      trendBox, valuesBox),
    await kpiTrendSection(path, windowEnd),
    h("div", { class: "grid-2" },
      section("Valve signature", "signature-title", await plot(loopId, "signature"),
        h("p", { class: "help" }, "Dots: the samples of the analysed window. Pink: the fitted "
          + "ellipse; black bar: its width along OP, the apparent stiction. Orange: the fitted "
          + "stiction model (valve S, J and process) replayed on the measured OP: its predicted "
          + "PV, and its valve position MV.")),
      section("Spectrum and autocorrelation", "spectrum-title", await plot(loopId, "spectrum"))),
    section("Stick-jump episodes", "episodes-title",
      h("p", { class: "help" }, "Where the valve held while OP moved, then jumped: the "
        + "evidence of a valve that sticks without a sustained cycle."),
      episodesTable(health.episodes, "No stick-jump episodes in the analysed window.")),
    h("div", { class: "grid-2" },
      section("Detection methods", "methods-title", methodsTable(diagnosis)),
      section("Stiction estimate", "estimate-title", estimateFacts(diagnosis),
        await plot(loopId, "history"))),
    h("div", { class: "grid-2" },
      section("Nyquist plot: G Gc and -1/N(A)", "nyquist-title", nyquistUnavailable(diagnosis)
        ? unavailablePlot("nyquist", nyquistUnavailable(diagnosis)) : await plot(loopId, "nyquist"),
        h("p", { class: "help" }, "The loop (identified process and configured controller) "
          + "against the describing function of the estimated stiction; a limit cycle is "
          + "predicted where the curves meet (harmonic balance, thesis Eq. 3.16).")),
      adviceSection(`${path}/advice`, adviceUnavailable(diagnosis))),
    section("Model check", "model-check-title",
      h("p", {}, "Replays the loop's model on the current window: where the simulation "
        + "differs from the measured PV, the cause, the extended model and what it gains."),
      h("button", { type: "button", onclick: () => {
        location.hash = `#/loop/${encodeURIComponent(loopId)}/model-check`;
      } }, "Check the model")),
    // Full width: the alarm table's last column holds the operator's buttons.
    section("Alarms of this loop", "loop-alarms-title", alarmsBox),
    section("Tickets of this loop", "loop-tickets-title", ticketsBox));
  await showTrend();

  const refresh = async () => {
    const [now, alarms, tickets] = await Promise.all([
      api(`${path}/health?trend=1`), api(`/alarms?loop_id=${encodeURIComponent(loopId)}`),
      openTickets(`&loop_id=${encodeURIComponent(loopId)}`)]);
    if (now.latest && latest && now.latest.id !== latest.id) {
      await renderLoop(loopId);  // a new analysis: redraw everything
      return;
    }
    alarmsBox.replaceChildren(alarmsTable(alarms.data, refresh));
    ticketsBox.replaceChildren(ticketsTable(tickets));
  };
  await refresh();
  startRefresh(refresh);
}

/* ------------------------------------------------------------------ unit page */

function signalName(signal) {
  // The unit diagnosis names signals "op_LOOP" and "pv_LOOP".
  const [role, ...loop] = signal.split("_");
  return [role.toUpperCase(), " of ", loopLink(loop.join("_"))];
}

function stickyValvesList(diagnosis, valves, loopsById) {
  // The size shown first is the valve's combined estimate over its confirming windows,
  // the one /loops, the overview and the ticket show; this window's own estimate of the
  // unit diagnosis follows it as evidence (one window alone moves more).
  if (diagnosis.sticky_valves.length === 0) {
    return h("p", { class: "empty" }, "No valve of this unit is named sticky.");
  }
  return h("ol", { id: "sticky-valves" }, diagnosis.sticky_valves.map((v) => {
    const loop = loopsById.get(v.loop);
    const combined = loop && loop.S !== null && loop.S !== undefined;
    // Without the process gain one window pins only K·J: its J is no estimate (QA).
    const windowSize = v.S === null ? "" : `S ${num(v.S)} %, ${v.J_product_only
      ? "J not resolved (only K·J)" : `J ${num(v.J)} %`}`;
    return h("li", { "data-loop-id": v.loop },
      h("strong", {}, valves.get(v.loop) || v.loop), " (", loopLink(v.loop), "): ",
      `confidence ${num(v.confidence)}, cycle ${num(v.period_s, 0)} s`,
      combined ? h("span", { class: "combined-size" },
        `, S ${num(loop.S)} %, J ${num(loop.J)} % (combined over its windows, as on its ticket)`)
        : (windowSize ? `, ${windowSize}` : ""),
      h("div", { class: "sub" },
        combined && windowSize ? `This window: ${windowSize}; ${v.reason}` : v.reason));
  }));
}

function oscillationGroup(group, index, valves) {
  // One plant-wide oscillation: its loops, the surrogate nonlinearity ranking of every OP
  // and PV (thesis chapter 2, step 3) and each loop's evidence.
  // The API names valves by their tags: sticky_valves has the tags, sticky_loops the loops.
  const sticky = new Set(group.sticky_loops);
  const rows = group.ranking.map((r, i) => {
    const loop = r.signal.split("_").slice(1).join("_");
    return h("tr", { "data-signal": r.signal },
      h("td", {}, i + 1), h("th", { scope: "row" }, signalName(r.signal)),
      h("td", {}, num(r.nonlinearity, 2)),
      h("td", {}, sticky.has(loop) ? pill(`sticky valve ${valves.get(loop) || loop}`, "bad")
        : "—"));
  });
  const id = `group-${index}`;
  return h("article", { class: "oscillation-group", "aria-labelledby": id },
    h("h3", { id }, `Oscillation of ${num(group.period_s, 0)} s (${num(group.cycles, 1)} `
      + "cycles in the window): ",
      group.loops.flatMap((l, i) => (i ? [", ", loopLink(l)] : [loopLink(l)]))),
    table(`Nonlinearity ranking of oscillation ${index + 1}`,
      ["Rank", "Signal", "Nonlinearity index", "Named"], rows, "No signal could be ranked."),
    h("ul", { class: "evidence" }, group.evidence.map((e) =>
      h("li", {}, loopLink(e.loop), `: ${e.note}`))),
    group.note ? h("p", { class: "help" }, group.note) : null);
}

async function unitDiagnosis(unitId, valves, loopsById) {
  // Runs the unit diagnosis on the latest windows: it takes a moment, so the page shows
  // the loops first and this fills in when it arrives.
  try {
    const diagnosis = await analysis(`/units/${encodeURIComponent(unitId)}/diagnosis`);
    const skipped = diagnosis.loops_without_complete_window;
    return [
      section("Sticky valves, most certain first", "sticky-title",
        stickyValvesList(diagnosis, valves, loopsById),
        h("p", { class: "help" }, `Diagnosed together on the window ending `
          + `${utc(diagnosis.window_end)}: ${diagnosis.loops.length} loops, `
          + `${diagnosis.samples} samples each.`
          + (skipped.length ? ` Left out (gaps in OP or PV): ${skipped.join(", ")}.` : ""))),
      section("Common oscillations and the ranking that names the valves", "common-title",
        diagnosis.groups.length
          ? diagnosis.groups.map((g, i) => oscillationGroup(g, i, valves))
          : h("p", { class: "empty" }, "No oscillation is shared by loops of this unit."),
        h("p", { class: "help" }, "Signals that oscillate together are ranked by their "
          + "surrogate nonlinearity index (highest first); a valve is named sticky when its "
          + "own stiction model is needed to explain its loop.")),
    ];
  } catch (error) {
    return [h("p", { class: "unavailable", role: "status" },
      `Unit diagnosis not available: ${error.message}`)];
  }
}

async function renderUnit(unitId) {
  const main = document.getElementById("main");
  const [units, loops] = await Promise.all([api("/units"),
    api(`/units/${encodeURIComponent(unitId)}`)]);
  const unit = units.data.find((u) => u.id === unitId) || { id: unitId, name: unitId };
  const valves = new Map(loops.data.map((l) => [l.id, l.valve_asset || l.id]));
  const diagnosisBox = h("div", { id: "unit-diagnosis", class: "grid-2", "aria-busy": "true" },
    h("p", { class: "unavailable" }, "Diagnosing the unit's loops together…"));
  const cards = await Promise.all(rankByHealth(loops.data).map(async (l) => h("article",
    { class: "card loop-card", "aria-labelledby": `card-${l.id}` },
    h("h3", { id: `card-${l.id}` }, loopLink(l.id), " ", h("span", { class: "sub" }, l.name)),
    definitionList([["Health", l.health === null ? "unknown" : num(l.health, 0)],
      ["Oscillation", oscillationText(l)], ["Valve", verdictPill(l.verdict, l.confidence)]]),
    await plot(l.id, "trend"))));
  main.replaceChildren(
    h("p", { class: "crumbs" }, h("a", { href: "#/" }, "Plant overview")),
    h("h1", {}, unit.name || unit.id, " ", h("span", { class: "sub" }, `unit ${unit.id}`)),
    diagnosisBox,
    h("section", { class: "side-by-side", "aria-label": "Loops of the unit side by side" },
      cards));
  diagnosisBox.replaceChildren(...await unitDiagnosis(unitId, valves,
    new Map(loops.data.map((l) => [l.id, l]))));
  diagnosisBox.removeAttribute("aria-busy");
}

/* ------------------------------------------------------------------ model check page */

function percent(fraction) {
  if (fraction === null || fraction === undefined) return "—";
  const rounded = Math.round(100 * fraction) || 0;  // no "-0"
  return `${rounded > 0 ? "+" : ""}${rounded} %`;
}

function parameterText(parameters) {
  // Parameters may nest: a valve that sticks differently opening and closing has an object
  // of S and J for each direction.
  const entries = Object.entries(parameters || {});
  if (entries.length === 0) return "—";
  const value = (k, v) => (typeof v === "number" ? num(v, 3) + parameterUnit(k)
    : v && typeof v === "object" ? `(${parameterText(v)})` : v);
  return entries.map(([k, v]) => `${k} ${value(k, v)}`).join(", ");
}

/** The unit of a model parameter (the model file's: times in s, valve sizes, positions and
 * load amplitudes in % of span, a load's phase in rad); none for gains and ratios. */
function parameterUnit(key) {
  if (["tau", "theta", "Ti", "Td", "period", "dt"].includes(key)) return " s";
  if (/^(S|J|fs|fd|low|high|amplitude)$|_(S|J|fs|fd)$/.test(key)) return " %";
  return key === "phase" ? " rad" : "";
}

function modelFacts(model) {
  // A model of issue 8: process, controller and valve, each an object of parameters.
  return definitionList(["process", "controller", "valve"].filter((part) => model[part])
    .map((part) => [part, parameterText(model[part])]));
}

function gainTable(check) {
  const { baseline, gain } = check;
  const rows = [
    ["NMSE on held-out data", num(gain.nmse_before, 4), num(gain.nmse_after, 4)],
    ["Closed-loop period error", percent(gain.period_error_before),
      percent(gain.period_error_after)],
    ["Closed-loop amplitude error", percent(gain.amplitude_error_before),
      percent(gain.amplitude_error_after)],
  ].map(([what, before, after]) => h("tr", {}, h("th", { scope: "row" }, what),
    h("td", {}, before), h("td", {}, after)));
  return h("div", { id: "model-check-gain" },
    table("The gain of the extended model", ["Measure", "Base model", "Extended model"], rows,
      ""),
    h("p", { class: "help" }, `Measurement noise alone would give an NMSE of about `
      + `${num(baseline.noise_nmse, 4)}: no model can do better.`));
}

function candidatesTable(check) {
  const rows = check.candidates.map((c) => h("tr", { "data-effect": c.effect,
    class: c.effect === check.cause.effect ? "chosen" : null },
  h("th", { scope: "row" }, c.effect.replace(/_/g, " ")),
  h("td", {}, parameterText(c.parameters)),
  h("td", {}, num(c.nmse_test, 4)),
  h("td", {}, percent(c.improvement)),
  h("td", {}, c.note || "")));
  return table("Effects tried", ["Effect", "Fitted parameters", "Held-out NMSE",
    "Error removed", "Note"], rows, "No effect was tried.");
}

async function modelCheckResult(loopId, check) {
  const cause = check.cause;
  const figure = await plot(loopId, "model-check", {},
    { overlay: check.overlay, cause: check.cause });
  return [
    section("Measured and simulated PV", "overlay-title", figure,
      h("p", { class: "help" }, `Window ${utc(check.window_start)} to ${utc(check.window_end)}, `
        + `${check.samples} samples; each model is driven by the measured OP.`)),
    h("div", { class: "grid-2" },
      section("Findings", "findings-title",
        h("ol", { id: "findings" }, check.findings.map((f) => h("li", {}, f))),
        ...(check.causes || [cause]).map((c, i) => h("p", {},
          h("strong", {}, i === 0 ? "Cause: " : "Second cause: "), c.effect.replace(/_/g, " "),
          ` (confidence ${num(c.confidence)}; ${parameterText(c.parameters)}`
          + (c.runner_up ? `; runner-up ${c.runner_up.replace(/_/g, " ")})` : ")"))),
        ...(check.notes || []).map((note) => h("p", { class: "note" }, note))),
      section("Gain", "gain-title", gainTable(check))),
    h("div", { class: "grid-2" },
      section("Base model", "base-model-title",
        h("p", { class: "help" }, check.model_source === "identified"
          ? "Identified from the window." : "As given."), modelFacts(check.base_model)),
      section("Extended model", "extended-model-title", modelFacts(check.extended_model))),
    section("Effects tried", "candidates-title", candidatesTable(check)),
  ];
}

async function renderModelCheck(loopId) {
  const main = document.getElementById("main");
  const path = `/loops/${encodeURIComponent(loopId)}`;
  const loop = await api(path);
  const result = h("div", { id: "model-check-result" });
  const again = h("button", { type: "button" }, "Check again");
  const page = session.page;
  const check = async () => {
    again.disabled = true;
    result.setAttribute("aria-busy", "true");
    result.replaceChildren(h("p", { class: "unavailable" },
      "Checking the model on the current window; this takes a few seconds…"));
    try {
      const answer = await analysis(`${path}/model-check`, { method: "POST" });
      const parts = await modelCheckResult(loopId, answer);
      if (page !== session.page) return;  // the user went elsewhere meanwhile
      result.replaceChildren(...parts);
      announce(`Model check of ${loopId} done: ${answer.cause.effect === "none"
        ? "no effect found" : answer.cause.effect.replace(/_/g, " ")}`);
    } catch (error) {
      result.replaceChildren(h("p", { class: "error", role: "alert" },
        `Model check not available: ${error.message}`));
    } finally {
      again.disabled = false;
      result.removeAttribute("aria-busy");
    }
  };
  again.addEventListener("click", check);
  main.replaceChildren(
    h("p", { class: "crumbs" }, h("a", { href: "#/" }, "Plant overview"),
      loop.unit ? [" › ", h("a", { href: `#/unit/${encodeURIComponent(loop.unit)}` }, loop.unit)]
        : null, " › ", loopLink(loopId)),
    h("h1", {}, `Model check: ${loopId} `, h("span", { class: "sub" }, loop.name)),
    h("p", {}, "The loop's model (identified from the window) replayed on the current window: "
      + "what the simulation gets wrong, the effect that explains it, and how much the "
      + "extended model gains. ", again),
    result);
  await check();
}

/* ------------------------------------------------------------------ ticket view */

/** A ticket's evidence keys as a planner reads them: the name, and the unit of the value. */
const EVIDENCE_NAMES = {
  S: ["S (stick band + deadband)", "% of valve span"],
  J: ["J (slip jump)", "% of valve span"],
  S_interval: ["S, 95 % interval", "% of valve span"],
  J_interval: ["J, 95 % interval", "% of valve span"],
  fs: ["fs (He's model)", "% of valve span"],
  fd: ["fd (He's model)", "% of valve span"],
  episode_S: ["S from the episodes", "% of span"],
  episode_stick_band: ["OP travel while PV held", "% of span"],
  op_travel: ["OP travel in the window", "% of span"],
  period_s: ["Period", "s"],
  amplitude_op: ["OP amplitude", "% of span"],
  amplitude_pv: ["PV amplitude", "% of span"],
  episodes_found: ["Stick-jump episodes found", ""],
  size_windows: ["Windows combined in S and J", ""],
  size_check: ["Episodes and Hammerstein", ""],
  confirmations: ["Confirmations (separate windows)", ""],
};

function evidenceValue(key, value) {
  const unit = (EVIDENCE_NAMES[key] || [])[1];
  const suffix = unit ? ` ${unit}` : "";
  if (Array.isArray(value)) return `${num(value[0], 2)} to ${num(value[1], 2)}${suffix}`;
  if (key.startsWith("window") && typeof value === "number") return utc(value);
  if (typeof value === "number" && !Number.isInteger(value)) {
    return `${num(value, unit === "s" ? 1 : 3)}${suffix}`;
  }
  return `${String(value)}${suffix}`;
}

async function renderTicket(ticketId) {
  const main = document.getElementById("main");
  const ticket = await api(`/tickets/${encodeURIComponent(ticketId)}`);
  const e = ticket.evidence || {};
  const trendParams = e.window_start && e.window_end ? { start: e.window_start, end: e.window_end }
    : {};
  // The plots the ticket links to (evidence.plots); the trend over the evidence window.
  const kinds = Object.keys(e.plots || { trend: 1, signature: 1, spectrum: 1 });
  const figures = await Promise.all(kinds.map((kind) =>
    plot(ticket.loop_id, kind, kind === "trend" ? trendParams : {})));
  const numbers = Object.entries(e).filter(([, v]) => v === null || typeof v !== "object"
    || (Array.isArray(v) && v.length === 2 && v.every((x) => typeof x === "number")));
  main.replaceChildren(
    h("p", { class: "crumbs no-print" }, h("a", { href: "#/" }, "Plant overview"), " › ",
      loopLink(ticket.loop_id)),
    h("article", { class: "ticket", "aria-labelledby": "ticket-title" },
      h("h1", { id: "ticket-title" }, `Ticket #${ticket.id}: ${ticket.title}`),
      h("button", { type: "button", class: "no-print", onclick: () => window.print() },
        "Print"),
      definitionList([["Valve", ticket.valve_asset], ["Loop", ticket.loop_id],
        ["Location", ticket.location || "—"], ["State", ticket.state],
        ["Priority", ticket.priority], ["Malfunction since", utc(ticket.malfunction_start)],
        ["Opened", utc(ticket.created_at)]]),
      // The long text as the CMMS gets it, but for its episode lines: the table below
      // lists the same episodes (they were on the page twice, 20 lines each).
      h("p", { class: "description" }, ticket.description.split("\n")
        .filter((line) => !/^Episode \d+: hold /.test(line)).join("\n")),
      h("h2", {}, "Evidence"),
      table("Evidence", ["Quantity", "Value"], numbers.map(([k, v]) =>
        h("tr", { "data-evidence": k }, h("th", { scope: "row" },
          (EVIDENCE_NAMES[k] || [k.replace(/_/g, " ")])[0]), h("td", {}, evidenceValue(k, v)))),
      "No evidence recorded."),
      h("h3", {}, "Stick-jump episodes"),
      episodesTable(e.episodes, "No stick-jump episodes recorded."),
      h("div", { class: "evidence-plots" }, figures),
      h("p", { class: "help" }, "Signature and spectrum: the latest analysis of the loop."),
      h("h2", {}, "History"),
      table("Ticket history", ["At", "From", "To", "By", "Note"], ticket.events.map((ev) =>
        h("tr", {}, h("td", {}, utc(ev.at)), h("td", {}, ev.from_state || "—"),
          h("td", {}, ev.to_state), h("td", {}, ev.actor), h("td", {}, ev.note))),
      "No changes yet.")));
}

/* ------------------------------------------------------------------ routing */

async function route() {
  stopRefresh();
  session.page += 1;
  const main = document.getElementById("main");
  const [path, query] = location.hash.replace(/^#/, "").split("?");
  const parts = (path || "/").split("/").filter(Boolean).map(decodeURIComponent);
  main.setAttribute("aria-busy", "true");
  try {
    if (parts[0] === "loop" && parts[1] && parts[2] === "model-check") {
      await renderModelCheck(parts[1]);
    } else if (parts[0] === "loop" && parts[1]) await renderLoop(parts[1]);
    else if (parts[0] === "unit" && parts[1]) await renderUnit(parts[1]);
    else if (parts[0] === "ticket" && parts[1]) await renderTicket(parts[1]);
    else await renderOverview(new URLSearchParams(query || ""));
    const heading = main.querySelector("h1");
    document.title = heading ? `${heading.textContent} · loopwatch` : "loopwatch";
  } catch (error) {
    if (!session.me) return;  // signed out on the way: the sign-in form is showing
    main.replaceChildren(h("h1", {}, "Not available"),
      h("p", { class: "error", role: "alert" }, error.message),
      h("p", {}, h("a", { href: "#/" }, "Back to the plant overview")));
  } finally {
    main.removeAttribute("aria-busy");
  }
}

function setLargeText(on) {
  document.documentElement.classList.toggle("large-text", on);
  document.getElementById("large-text").setAttribute("aria-pressed", String(on));
  localStorage.setItem(LARGE_TEXT_STORAGE, on ? "1" : "");
}

async function start() {
  const largeText = document.getElementById("large-text");
  setLargeText(localStorage.getItem(LARGE_TEXT_STORAGE) === "1");
  largeText.addEventListener("click", () =>
    setLargeText(largeText.getAttribute("aria-pressed") !== "true"));
  document.getElementById("sign-out").addEventListener("click", () => signOut("Signed out."));
  window.addEventListener("hashchange", async () => {
    if (keyFromLink()) {  // a key link opened in this tab: sign in with it
      await signInAndRoute();
      return;
    }
    if (!session.me) return;
    await route();
    // The new page gets the focus, unless the user moved it into the page while it loaded
    const main = document.getElementById("main");
    if (!main.contains(document.activeElement) || document.activeElement === main) main.focus();
  });
  keyFromLink();
  if (!sessionStorage.getItem(KEY_STORAGE)) {
    renderSignIn("");
    return;
  }
  await signInAndRoute();
}

/** Takes the key of a #key=KEY or #key=KEY&/PAGE link (the slash, or the page after a
 * trailing "&", may be missing) into sessionStorage and leaves #/PAGE (or #/) in the
 * address bar; whether there was one. */
function keyFromLink() {
  const fragment = location.hash.match(/^#key=([^&]+)(?:&\/?(.*))?$/);
  if (!fragment) return false;
  sessionStorage.setItem(KEY_STORAGE, decodeURIComponent(fragment[1]));
  history.replaceState(null, "", `${location.pathname}#/${fragment[2] || ""}`);
  return true;
}

async function signInAndRoute() {
  try {
    await signIn();
  } catch (error) {
    signOut(`The stored key was not accepted: ${error.message}`);
    return;
  }
  await route();
}

document.addEventListener("DOMContentLoaded", start);
