// slc-gateway status page: asks /api/status and the register view once a second; read-only.
"use strict";

const PERIOD_MS = 1000;
const $ = (id) => document.getElementById(id);
let lastStatus = null;
let view = null; // {unit, table, start, count}

function el(tag, className, text) {
  const node = document.createElement(tag);
  if (className) node.className = className;
  if (text !== undefined && text !== null) node.textContent = String(text);
  return node;
}

function cell(row, label, className, text) {
  const td = el("td", className, text);
  if (label) td.dataset.label = label;
  row.appendChild(td);
  return td;
}

function seconds(value) {
  // an age or a duration in seconds, short: 0.4 s, 12 s, 3 min, 2 h 5 min, 3 d
  if (value === null || value === undefined) return "never";
  if (value < 10) return value.toFixed(1) + " s";
  if (value < 120) return Math.round(value) + " s";
  if (value < 7200) return Math.floor(value / 60) + " min";
  if (value < 172800) return Math.floor(value / 3600) + " h " + Math.floor((value % 3600) / 60) + " min";
  return Math.floor(value / 86400) + " d";
}

function clock(unixSeconds) {
  const date = new Date(unixSeconds * 1000);
  const sameDay = new Date().toDateString() === date.toDateString();
  const time = date.toLocaleTimeString([], {hour: "2-digit", minute: "2-digit", second: "2-digit"});
  return sameDay ? time : date.toLocaleDateString() + " " + time;
}

const number = (n) => Number(n).toLocaleString();

async function getJson(url) {
  const response = await fetch(url, {cache: "no-store"});
  const body = await response.json();
  if (!response.ok) throw new Error(body.error || response.status + " " + response.statusText);
  return body;
}

// --- links ---------------------------------------------------------------------------------

const ORDER = {down: 0, stale: 1, up: 2};

function renderLinks(status) {
  const filter = $("filter").value.trim().toLowerCase();
  let links = status.links.filter((link) => !filter ||
    [link.name, link.kind, link.controllers, link.port, String(link.unit), link.state].some(
      (text) => text.toLowerCase().includes(filter)));
  if ($("problems").checked) links = links.slice().sort((a, b) => ORDER[a.state] - ORDER[b.state]);
  const body = document.createElement("tbody");
  for (const link of links) {
    const row = el("tr", link.state);
    row.dataset.link = link.name;
    const state = cell(row, "", "");
    state.appendChild(el("span", "badge " + link.state, link.state));
    if (link.since !== null) {
      state.appendChild(el("div", "sub", "for " + seconds(status.time - link.since)));
      state.title = "since " + clock(link.since);
    }
    const name = cell(row, "", "");
    name.appendChild(el("div", "name", link.name));
    name.appendChild(el("div", "sub", [link.kind, link.controllers].filter(Boolean).join(" · ")));
    cell(row, "Unit", "num unit", link.unit);
    cell(row, "Port", "port", link.port);
    const plan = link.schedule;
    const limit = plan ? plan.stale_limit : link.stale_after;
    const age = cell(row, "Data age", "num age", seconds(link.data_age));
    if (link.data_age === null || (limit !== null && link.data_age >= limit)) {
      age.classList.add("age-stale");
    }
    age.title = limit === null ? "never stale" : "oldest fast-class value; stale at " + limit + " s " +
      "(stale_after " + link.stale_after + " s plus the fast class's refresh period)";
    renderRefresh(cell(row, "Refresh", "refresh", ""), plan);
    cell(row, "Transactions", "num", number(link.transactions));
    cell(row, "Errors", "num", number(link.errors));
    renderQuality(row, link.line);
    const error = cell(row, "Last error", "error" + (link.state === "up" ? " old" : ""), link.last_error || "–");
    if (link.last_error_at !== null) {
      error.textContent = clock(link.last_error_at) + "  " + (link.last_error || "");
    }
    body.appendChild(row);
  }
  $("links").replaceChild(body, $("links").tBodies[0]);
}

// The line's quality (/api/status "line"), in the order of the table's head; "–": the protocol
// has no such thing.
const QUALITY = [
  ["check_errors", "Check errors"], ["naks", "NAKs"], ["timeouts", "Timeouts"],
  ["retransmits", "Retransmits"], ["resyncs", "Resyncs"],
];

function renderQuality(row, line) {
  for (const [key, label] of QUALITY) {
    const value = line[key];
    const td = cell(row, label, "num quality " + key, value === null ? "–" : number(value));
    if (value) td.classList.add("counted");
  }
}

// The line's budget of a link: what the schedule achieves (docs/guide/freshness.md).
function renderRefresh(where, plan) {
  if (!plan) {
    where.textContent = "–";
    return;
  }
  const period = (name) => plan.refresh[name] === null ? "–" : seconds(plan.refresh[name]);
  where.appendChild(el("div", "", "fast " + period("fast") + " · slow " + period("slow")));
  const use = plan.line_use === null ? "" : " · line " + Math.round(100 * plan.line_use) + " %";
  where.appendChild(el("div", "sub", plan.demanded + "/" + plan.blocks + " read by clients: " + period("demanded") + use));
  if (plan.behind) where.appendChild(el("div", "sub bad", plan.behind));
  const bound = (name) => plan.age_bound[name] === null ? "–" : seconds(plan.age_bound[name]);
  where.title = "achieved refresh periods; every block is read within its age bound: fast " + bound("fast") +
    ", slow " + bound("slow") + ", read by clients " + bound("demanded") + "; mean transaction " +
    (plan.transaction_time === null ? "–" : seconds(plan.transaction_time));
}

function renderSummary(status) {
  const summary = $("summary");
  summary.replaceChildren();
  const total = status.links.length;
  const down = status.links.filter((link) => link.state === "down").length;
  const stale = status.links.filter((link) => link.state === "stale").length;
  const links = el("span");
  links.appendChild(el("b", "", status.up + "/" + total));
  links.appendChild(document.createTextNode(" links up"));
  summary.appendChild(links);
  if (down) summary.appendChild(el("span", "bad", down + " down"));
  if (stale) summary.appendChild(el("span", "bad", stale + " stale"));
  for (const server of status.servers) {
    summary.appendChild(el("span", "", server.name + ": " + server.connections + " clients, " +
      number(server.requests) + " requests, " + number(server.exceptions) + " exceptions"));
  }
  const spb = status.sparkplug;
  if (spb) {
    summary.appendChild(el("span", spb.state === "online" ? "" : "bad", "Sparkplug " + spb.state +
      " (bdSeq " + spb.bd_seq + "): " + spb.devices_online + "/" + spb.devices + " devices, " +
      number(spb.published) + " published, " + number(spb.commands) + " commands, " + number(spb.refused) +
      " refused"));
    const store = spb.store;
    if (store) {
      const text = store.failed ? "store off: " + store.failed :
        "store: " + number(store.messages) + " changes, " + number(store.bytes) + " bytes" +
        (store.oldest ? ", oldest " + store.oldest : "") + ", " + number(store.replayed) + " replayed, " +
        number(store.dropped) + " dropped";
      summary.appendChild(el("span", store.failed || store.dropped ? "bad" : "", text));
    }
  }
  const ua = status.opcua;
  if (ua) {
    summary.appendChild(el("span", "", "OPC UA: " + ua.sessions + " sessions, " + ua.subscriptions +
      " subscriptions, " + number(ua.monitored_items) + " monitored items, " + ua.publish_rate +
      " changes/s, " + number(ua.rejected_logins) + " rejected logins"));
  }
  summary.appendChild(el("span", "", "updated " + clock(status.time)));
  $("version").textContent = "· slc-gateway " + status.version;
}

function fillUnits(status) {
  const select = $("unit");
  const units = status.links.map((link) => link.unit + " – " + link.name).join("|");
  if (select.dataset.units === units) return;
  const chosen = select.value;
  select.replaceChildren();
  for (const link of status.links) {
    const option = el("option", "", link.unit + " – " + link.name);
    option.value = String(link.unit);
    select.appendChild(option);
  }
  select.dataset.units = units;
  if (chosen) select.value = chosen;
  if (view === null && status.links.length) readForm();
}

async function refreshStatus() {
  try {
    lastStatus = await getJson("api/status");
    $("connection").textContent = "";
    renderSummary(lastStatus);
    renderLinks(lastStatus);
    fillUnits(lastStatus);
  } catch (error) {
    $("connection").textContent = "gateway not reachable: " + error.message;
  }
}

// --- registers -----------------------------------------------------------------------------

function reference(table, address) {
  const prefix = {coil: "0", discrete: "1", input: "3", holding: "4"}[table];
  return prefix + String(address + 1).padStart(5, "0");
}

function float32(high, low) {
  const buffer = new DataView(new ArrayBuffer(4));
  buffer.setUint16(0, high);
  buffer.setUint16(2, low);
  return buffer.getFloat32(0);
}

function shown(entry, next) {
  if (entry.value === null) return "–";
  if (entry.type === "float32" && next && next.value !== null) {
    const [high, low] = entry.word_order === "low-first" ? [next.value, entry.value] : [entry.value, next.value];
    return entry.value + "  (" + Number(float32(high, low).toPrecision(7)) + ")";
  }
  if (entry.type === "int16" && entry.value > 32767) return entry.value + "  (" + (entry.value - 65536) + ")";
  return String(entry.value);
}

function renderRegisters(data) {
  const body = document.createElement("tbody");
  data.values.forEach((entry, k) => {
    const row = el("tr", entry.state);
    row.dataset.address = entry.address;
    cell(row, "", "num", entry.address);
    cell(row, "", "num", reference(data.table, entry.address));
    cell(row, "", "tag", entry.tag || "");
    cell(row, "", "num value", shown(entry, data.values[k + 1]));
    const age = cell(row, "", "num age", entry.state === "unmapped" ? "" : seconds(entry.age));
    if (entry.state === "stale") age.classList.add("age-stale");
    cell(row, "", "state " + entry.state, entry.state);
    body.appendChild(row);
  });
  $("registers").replaceChild(body, $("registers").tBodies[0]);
  const stale = data.values.filter((entry) => entry.state !== "fresh" && entry.state !== "unmapped").length;
  const note = $("view-note");
  note.className = "note" + (stale ? " bad" : "");
  note.textContent = "unit " + data.unit + " (" + data.link + "), " + data.table + " " + data.start + "–" +
    (data.start + data.count - 1) + ": " + staleRule(data) + (stale ? " — " + stale + " not fresh now" : "");
}

function staleRule(data) {
  // when a value of the view is stale (the rule Modbus answers 0x0B by), for a polled unit or not
  if (!data.polled) {
    return "not polled: values are what the peer last sent, ages since it sent them; " + (data.stale_after === null
      ? "they never go stale" : "they go stale when the peer is silent for stale_after (" + data.stale_after +
        " s): Modbus answers them 0x0B");
  }
  return "ages are since each value was read; values older than stale_after (" + data.stale_after +
    " s) beyond their scan period are stale: Modbus answers them 0x0B";
}

async function refreshRegisters() {
  if (view === null) return;
  const url = "api/units/" + encodeURIComponent(view.unit) + "/" + encodeURIComponent(view.table) +
    "?start=" + view.start + "&count=" + view.count;
  try {
    renderRegisters(await getJson(url));
  } catch (error) {
    const note = $("view-note");
    note.className = "note bad";
    note.textContent = error.message;
    $("registers").tBodies[0].replaceChildren();
  }
}

function readForm() {
  view = {unit: $("unit").value, table: $("table").value, start: $("start").value || "0",
          count: $("count").value || "16"};
  const query = new URLSearchParams(view);
  history.replaceState(null, "", "#" + query.toString());
}

function restoreForm() {
  const query = new URLSearchParams(location.hash.slice(1));
  if (!query.has("unit")) return;
  for (const key of ["table", "start", "count"]) if (query.has(key)) $(key).value = query.get(key);
  const option = el("option", "", query.get("unit"));
  option.value = query.get("unit");
  $("unit").appendChild(option);
  $("unit").value = query.get("unit");
  readForm();
}

async function tick() {
  await Promise.all([refreshStatus(), refreshRegisters()]);
  setTimeout(tick, PERIOD_MS);
}

document.addEventListener("DOMContentLoaded", () => {
  $("view").addEventListener("submit", (event) => {
    event.preventDefault();
    readForm();
    refreshRegisters();
  });
  for (const id of ["unit", "table"]) $(id).addEventListener("change", () => { readForm(); refreshRegisters(); });
  $("filter").addEventListener("input", () => lastStatus && renderLinks(lastStatus));
  $("problems").addEventListener("change", () => lastStatus && renderLinks(lastStatus));
  restoreForm();
  tick();
});
