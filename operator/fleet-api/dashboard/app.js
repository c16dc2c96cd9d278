// LeKiwi fleet dashboard. It talks only to the Fleet API (/api/v1) of the gateway that served
// it, with the bearer token the user pasted (kept in this tab's sessionStorage), so it can do
// exactly what RBAC allows that token. Views: #/fleet, #/robots/NAMESPACE/NAME, #/rollouts.
// The shown view follows a GraphQL subscription (graphql-transport-ws on /api/v1/graphql): each
// change it announces re-reads the view (coalesced), and a slow poll catches what it does not
// announce (deletions); without a subscription the view polls every REFRESH_MS. Either way the
// API answers from the gateway's watch-fed cache, so this costs the API server nothing. Text that comes from robots is set
// with textContent, never parsed as HTML; the page runs under a strict Content-Security-Policy.
'use strict';

const REFRESH_MS = 2000;
const SUBSCRIBED_REFRESH_MS = 15000; // the safety net while a subscription announces changes
const COALESCE_MS = 200; // changes within this window cause one re-read
const MIN_GAP_MS = 1000; // and re-reads are at least this far apart (a busy fleet changes often)
const MAX_PAGES = 10; // of 1,000 items, for the lists that are read whole
const MAX_ROWS = 500;
const PHASES = ['Online', 'Offline', 'Unknown', 'Pending', 'Maintenance'];
const STATES = ['Updated', 'Updating', 'Waiting', 'Pending', 'Skipped', 'Failed', 'RolledBack'];
const CHARTS = [
  ['cpu_percent', 'CPU %', 100],
  ['memory_percent', 'Memory %', 100],
  ['temperature_c', 'Temperature °C', null],
];

const S = {
  token: sessionStorage.getItem('lekiwi.token') || '',
  ns: sessionStorage.getItem('lekiwi.namespace') || 'default',
  access: null,
  timer: null,
  generation: 0,
  socket: null,
  live: 'polling',
  filters: { selector: '', phase: '', release: '' },
};

class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

/** One Fleet API call; throws ApiError with the API's own message. */
async function api(path, method = 'GET') {
  const response = await fetch(path, {
    method,
    cache: 'no-store',
    headers: { Authorization: 'Bearer ' + S.token, Accept: 'application/json' },
  });
  let body = null;
  try {
    body = await response.json();
  } catch (_) {
    body = null;
  }
  if (!response.ok) {
    const message = (body && body.message) || response.status + ' ' + response.statusText;
    if (response.status === 401) logout('The token was refused: ' + message);
    throw new ApiError(response.status, message);
  }
  return body;
}

/** Every item of a paged list, at most MAX_PAGES pages. */
async function listAll(path, query) {
  const items = [];
  let next = null;
  for (let page = 0; page < MAX_PAGES; page++) {
    const q = new URLSearchParams(query);
    q.set('limit', '1000');
    if (next) q.set('continue', next);
    const body = await api(path + '?' + q.toString());
    items.push(...body.items);
    next = body.continue;
    if (!next) return { items, complete: true };
  }
  return { items, complete: false };
}

/** An element with attributes (`text` sets textContent, `on…` adds a listener) and children. */
function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k === 'class') e.className = v;
    else if (k === 'text') e.textContent = v;
    else if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v === true ? '' : String(v));
  }
  for (const c of children.flat(Infinity)) {
    if (c === null || c === undefined) continue;
    e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return e;
}

const $ = (id) => document.getElementById(id);
const ns = () => encodeURIComponent(S.ns);

function age(time) {
  if (!time) return '—';
  const s = Math.max(0, Math.round((Date.now() - Date.parse(time)) / 1000));
  if (s < 60) return s + 's ago';
  if (s < 3600) return Math.floor(s / 60) + 'm ago';
  if (s < 86400) return Math.floor(s / 3600) + 'h ago';
  return Math.floor(s / 86400) + 'd ago';
}

/** `ms` (Unix milliseconds) as a local date and time, `2026-12-05 14:03:07`. */
function dateTime(ms) {
  const d = new Date(ms);
  const p = (n) => String(n).padStart(2, '0');
  return d.getFullYear() + '-' + p(d.getMonth() + 1) + '-' + p(d.getDate()) + ' ' + p(d.getHours()) + ':' + p(d.getMinutes()) + ':' + p(d.getSeconds());
}

/**
 * When a robot was last heard from: `lastSeen` (its live heartbeat on the gateway that holds
 * it), else the heartbeat time its status last recorded (refreshed only every few minutes).
 */
function heartbeat(lastSeen, status) {
  const written = status.lastHeartbeatTime;
  const seen = lastSeen || written;
  return el('span', {
    class: 'heartbeat',
    'data-last-seen': seen,
    'data-status-time': written,
    title: seen ? 'heartbeat ' + dateTime(Date.parse(seen)) + (written ? '; status written ' + dateTime(Date.parse(written)) : '') : null,
    text: age(seen),
  });
}

/** A robot's hardware (`spec.hardware`) in one line. */
function hardware(h) {
  if (!h) return '—';
  const cameras = h.cameras && h.cameras.length ? 'cameras: ' + h.cameras.join(', ') : null;
  const serial = h.serial ? 'serial ' + h.serial : null;
  const parts = [h.model, h.computer, serial, cameras, h.notes].filter(Boolean);
  return parts.length ? parts.join(' · ') : '—';
}

const num = (v, unit) => (v === undefined || v === null ? '—' : v.toFixed(1) + unit);
const badge = (phase) => el('span', { class: 'badge phase-' + (phase || 'Pending'), text: phase || 'Pending' });

function setStatus(text, error) {
  const s = $('status');
  s.textContent = text;
  s.className = error ? 'status error' : 'status';
}

// ---------------------------------------------------------------- login and navigation

function logout(why) {
  S.token = '';
  S.access = null;
  sessionStorage.removeItem('lekiwi.token');
  stop();
  $('nav').hidden = true;
  $('view').replaceChildren();
  $('login').hidden = false;
  $('login-namespace').value = S.ns;
  $('login-error').textContent = why || '';
  setStatus('');
}

async function loadAccess() {
  S.access = await api('/api/v1/namespaces/' + ns() + '/access');
  $('whoami').textContent = S.access.user + ' in ' + S.ns;
}

async function login(event) {
  event.preventDefault();
  S.token = $('login-token').value.trim();
  S.ns = $('login-namespace').value.trim() || 'default';
  try {
    await loadAccess();
  } catch (e) {
    $('login-error').textContent = e.message;
    return;
  }
  sessionStorage.setItem('lekiwi.token', S.token);
  sessionStorage.setItem('lekiwi.namespace', S.ns);
  $('login-token').value = '';
  $('login').hidden = true;
  $('nav').hidden = false;
  $('namespace').value = S.ns;
  if (!location.hash || location.hash === '#/') location.hash = '#/fleet';
  else render();
}

async function changeNamespace() {
  const value = $('namespace').value.trim();
  if (!value || value === S.ns) return;
  S.ns = value;
  sessionStorage.setItem('lekiwi.namespace', S.ns);
  try {
    await loadAccess();
  } catch (e) {
    setStatus(e.message, true);
  }
  location.hash = location.hash.startsWith('#/rollouts') ? '#/rollouts' : '#/fleet';
  render();
}

function stop() {
  S.generation++;
  clearTimeout(S.timer);
  if (S.socket) S.socket.close(1000, 'view changed');
  S.socket = null;
  S.live = 'polling';
}

/**
 * Subscribes to `query` over graphql-transport-ws and calls `changed` for every message; calls
 * `lost` when the subscription cannot start or ends. Browsers cannot set headers on a
 * WebSocket: the token goes in connection_init, as the gateway expects.
 */
function subscribe(query, variables, changed, lost) {
  const url = (location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + '/api/v1/graphql';
  let socket;
  try {
    socket = new WebSocket(url, 'graphql-transport-ws');
  } catch (_) {
    lost();
    return null;
  }
  let ended = false;
  const end = () => {
    if (!ended) {
      ended = true;
      lost();
    }
  };
  socket.onopen = () => socket.send(JSON.stringify({ type: 'connection_init', payload: { authorization: 'Bearer ' + S.token } }));
  socket.onmessage = (event) => {
    let message;
    try {
      message = JSON.parse(event.data);
    } catch (_) {
      return;
    }
    if (message.type === 'connection_ack') {
      socket.send(JSON.stringify({ id: '1', type: 'subscribe', payload: { query, variables } }));
    } else if (message.type === 'ping') {
      socket.send(JSON.stringify({ type: 'pong' }));
    } else if (message.type === 'next' && !(message.payload && message.payload.errors)) {
      changed();
    } else if (message.type === 'error' || message.type === 'complete' || message.type === 'next') {
      socket.close(1000, 'subscription ended');
      end();
    }
  };
  socket.onclose = end;
  socket.onerror = end;
  return socket;
}

/** Shows a view: `setup` builds its frame once, `refresh` fills it now and every REFRESH_MS. */
function show(view) {
  stop();
  const generation = S.generation;
  const root = el('div');
  $('view').replaceChildren(root);
  const refresh = view.setup(root);
  let running = false;
  let again = false;
  let lastRun = 0;
  // One re-read at a time; a change announced meanwhile causes one more after it.
  const tick = async () => {
    if (generation !== S.generation) return;
    clearTimeout(S.timer);
    if (running) {
      again = true;
      return;
    }
    running = true;
    lastRun = Date.now();
    try {
      if (!document.hidden) await refresh();
      if (generation === S.generation) {
        const how = S.live === 'subscription' ? 'Live (subscription)' : 'Live (polling every ' + REFRESH_MS / 1000 + ' s)';
        setStatus(how + ' · updated ' + new Date().toLocaleTimeString());
      }
    } catch (e) {
      if (generation === S.generation && S.token) setStatus(e.message, true);
    }
    running = false;
    if (generation !== S.generation) return;
    if (again) {
      again = false;
      S.timer = setTimeout(tick, COALESCE_MS);
    } else {
      S.timer = setTimeout(tick, S.live === 'subscription' ? SUBSCRIBED_REFRESH_MS : REFRESH_MS);
    }
  };
  if (view.subscription) {
    let pending = null;
    S.live = 'subscription';
    S.socket = subscribe(
      view.subscription.query,
      view.subscription.variables,
      () => {
        if (generation !== S.generation || pending) return;
        const wait = Math.max(COALESCE_MS, lastRun + MIN_GAP_MS - Date.now());
        pending = setTimeout(() => {
          pending = null;
          tick();
        }, wait);
      },
      () => {
        if (generation !== S.generation) return;
        S.live = 'polling';
        S.socket = null;
        tick();
      },
    );
  }
  tick();
}

function render() {
  if (!S.token) return logout();
  const parts = location.hash.replace(/^#\/?/, '').split('/').map(decodeURIComponent);
  for (const a of document.querySelectorAll('nav a')) a.classList.remove('active');
  if (parts[0] === 'robots' && parts.length === 3) {
    $('nav-fleet').classList.add('active');
    show(robotView(parts[1], parts[2]));
  } else if (parts[0] === 'rollouts') {
    $('nav-rollouts').classList.add('active');
    show(rolloutsView());
  } else {
    $('nav-fleet').classList.add('active');
    show(fleetView());
  }
}

// ---------------------------------------------------------------- fleet

function fleetView() {
  let cards, tbody, note, problem;
  let asked = 0; // the latest read asked for; an older answer arriving later is dropped
  const setup = (root) => {
    const f = S.filters;
    const input = (key, placeholder) =>
      el('input', {
        id: 'filter-' + key,
        placeholder,
        value: f[key],
        oninput: (e) => {
          f[key] = e.target.value.trim();
          refresh().catch((err) => setStatus(err.message, true));
        },
      });
    const phase = el(
      'select',
      {
        id: 'filter-phase',
        onchange: (e) => {
          f.phase = e.target.value;
          refresh().catch((err) => setStatus(err.message, true));
        },
      },
      el('option', { value: '', text: 'every phase' }),
      PHASES.map((p) => el('option', { value: p, text: p, selected: p === f.phase })),
    );
    cards = el('div', { class: 'cards', id: 'counts' });
    note = el('p', { class: 'muted', id: 'robots-note' });
    problem = el('p', { class: 'alert', id: 'filter-error', role: 'alert', hidden: true });
    tbody = el('tbody');
    const head = ['Robot', 'Phase', 'Release', 'Healthy', 'Teleoperated', 'Last heartbeat', 'Battery', 'CPU', 'Gateway'];
    root.append(
      el('h2', { text: 'Fleet' }),
      cards,
      el('div', { class: 'filters' }, input('selector', 'label selector, e.g. lab=north'), phase, input('release', 'release version')),
      problem,
      note,
      el('table', { id: 'robots' }, el('thead', {}, el('tr', {}, head.map((h) => el('th', { text: h })))), tbody),
    );
    return refresh;
  };
  const refresh = async () => {
    const ask = ++asked;
    const query = {};
    if (S.filters.selector) query.labelSelector = S.filters.selector;
    if (S.filters.release) query.release = S.filters.release;
    const rowsQuery = new URLSearchParams(query);
    if (S.filters.phase) rowsQuery.set('phase', S.filters.phase);
    rowsQuery.set('limit', String(MAX_ROWS));
    let summary, page;
    try {
      // Counts from the summary (its size does not grow with the fleet), rows from one page.
      summary = await api('/api/v1/namespaces/' + ns() + '/summary?' + new URLSearchParams(query).toString());
      page = await api('/api/v1/namespaces/' + ns() + '/robots?' + rowsQuery.toString());
    } catch (e) {
      if (ask !== asked) return;
      if (!(e instanceof ApiError) || e.status !== 400) throw e;
      // A filter the API refuses (a malformed selector): nothing matches it, so nothing shows,
      // least of all the rows of the filter before.
      cards.replaceChildren();
      tbody.replaceChildren();
      note.textContent = '';
      problem.textContent = 'The filter is not valid: ' + e.message;
      problem.hidden = false;
      return;
    }
    if (ask !== asked) return;
    problem.hidden = true;
    problem.textContent = '';
    cards.replaceChildren(
      el('div', { class: 'card', id: 'count-total' }, el('div', { class: 'n', text: summary.total }), el('div', { class: 'label', text: 'robots' })),
      ...PHASES.map((p) =>
        el('div', { class: 'card', id: 'count-' + p }, el('div', { class: 'n', text: summary.phases[p] || 0 }), el('div', {}, badge(p))),
      ),
      el('div', { class: 'card', id: 'count-teleoperated' }, el('div', { class: 'n', text: summary.teleoperated }), el('div', { class: 'label', text: 'teleoperated' })),
      el('div', { class: 'card', id: 'count-unhealthy' }, el('div', { class: 'n', text: summary.unhealthy }), el('div', { class: 'label', text: 'unhealthy' })),
    );
    const matching = S.filters.phase ? summary.phases[S.filters.phase] || 0 : summary.total;
    note.textContent = page.continue
      ? 'Showing the first ' + page.items.length + ' of ' + matching + ' robots; filter to narrow.'
      : page.items.length + ' robots shown.';
    tbody.replaceChildren(...page.items.map(robotRow));
  };
  const subscription = {
    query: 'subscription ($ns: String!, $sel: String) { robotChanges(namespace: $ns, labelSelector: $sel) { name } }',
    // The whole namespace: the filters can change while the subscription stays.
    variables: { ns: S.ns, sel: null },
  };
  return { setup, subscription };
}

function robotRow(r) {
  const s = r.status || {};
  const name = r.metadata.name;
  const t = s.telemetry || {};
  const href = '#/robots/' + encodeURIComponent(r.metadata.namespace) + '/' + encodeURIComponent(name);
  const display = r.spec && r.spec.displayName;
  return el(
    'tr',
    { 'data-robot': name, 'data-phase': s.phase || 'Pending' },
    el('td', {}, el('a', { href, text: name }), display ? el('div', { class: 'muted display-name', text: display }) : null),
    el('td', {}, badge(s.phase)),
    el('td', { text: (s.currentRelease && s.currentRelease.version) || '—' }),
    el('td', { text: s.health ? (s.health.healthy ? 'yes' : 'no') : '—' }),
    el('td', { text: s.teleoperation && s.teleoperation.active ? 'yes' : 'no' }),
    el('td', {}, heartbeat(r.lastSeen, s)),
    el('td', { text: num(t.batteryPercent, ' %') }),
    el('td', { text: num(t.cpuPercent, ' %') }),
    el('td', { text: s.gateway || '—' }),
  );
}

// ---------------------------------------------------------------- one robot

function robotView(namespace, name) {
  // Polled: a subscription names no single robot, and this view re-reads charts and events too.
  const base = '/api/v1/namespaces/' + encodeURIComponent(namespace) + '/robots/' + encodeURIComponent(name);
  let shownName, content, missing, facts, conditions, charts, events;
  const setup = (root) => {
    shownName = el('span', { class: 'muted', id: 'robot-display-name' });
    facts = el('dl', { class: 'kv', id: 'robot-facts' });
    conditions = el('tbody');
    charts = el('div', { class: 'charts', id: 'charts' });
    events = el('tbody');
    missing = el(
      'div',
      { class: 'alert', id: 'robot-not-found', role: 'alert', hidden: true },
      el('strong', { text: 'Robot not found: ' + name }),
      el('p', { text: 'Namespace ' + namespace + ' has no robot named ' + name + '. It may have been deleted, or the link names another namespace.' }),
      el('a', { href: '#/fleet', text: 'Back to the fleet' }),
    );
    content = el(
      'div',
      { id: 'robot-content' },
      facts,
      el('h3', { text: 'Conditions' }),
      el('table', { id: 'conditions' }, el('thead', {}, el('tr', {}, ['Type', 'Status', 'Reason', 'Message', 'Since'].map((h) => el('th', { text: h })))), conditions),
      el('h3', { text: 'Telemetry (up to the last hour)' }),
      charts,
      el('h3', { text: 'Recent events, last hour (newest first)' }),
      el('table', { id: 'events' }, el('thead', {}, el('tr', {}, ['Time', 'Severity', 'Kind', 'Message'].map((h) => el('th', { text: h })))), events),
    );
    root.append(el('h2', {}, el('a', { href: '#/fleet', text: 'Fleet' }), ' / ', name, ' ', shownName), missing, content);
    return refresh;
  };
  const refresh = async () => {
    let view;
    try {
      view = await api(base);
    } catch (e) {
      if (!(e instanceof ApiError) || e.status !== 404) throw e;
      content.hidden = true;
      missing.hidden = false;
      return;
    }
    missing.hidden = true;
    content.hidden = false;
    const r = view.robot;
    const s = r.status || {};
    const spec = r.spec || {};
    const v = view.vitals || {};
    const sys = s.system || {};
    const row = (k, value) => [el('dt', { text: k }), el('dd', {}, value)];
    shownName.textContent = spec.displayName ? '(' + spec.displayName + ')' : '';
    facts.replaceChildren(
      ...row('Display name', spec.displayName || '—'),
      ...row('Hardware', hardware(spec.hardware)),
      ...row('System', [sys.os, sys.arch, sys.cpus ? sys.cpus + ' CPUs' : null, sys.memoryBytes ? (sys.memoryBytes / 2 ** 30).toFixed(1) + ' GiB' : null].filter(Boolean).join(' · ') || '—'),
      ...row('Phase', badge(s.phase)),
      ...row('Release', (s.currentRelease && s.currentRelease.version) || '—'),
      ...row('Agent', s.agentVersion || '—'),
      ...row('Gateway', s.gateway || '—'),
      ...row('Address', s.address || '—'),
      ...row('Health', s.health ? (s.health.healthy ? 'healthy' : 'unhealthy') + (s.health.message ? ': ' + s.health.message : '') : '—'),
      ...row('Teleoperated', s.teleoperation && s.teleoperation.active ? 'yes' : 'no'),
      ...row('Last heartbeat', heartbeat(view.lastSeen, s)),
      ...row('Vitals', 'CPU ' + num(v.cpuPercent, ' %') + ' · memory ' + num(v.memoryPercent, ' %') + ' · temperature ' + num(v.temperatureCelsius, ' °C') + ' · battery ' + num(v.batteryPercent, ' %')),
    );
    conditions.replaceChildren(
      ...(s.conditions || []).map((c) =>
        el('tr', { 'data-condition': c.type }, el('td', { text: c.type }), el('td', { text: c.status }), el('td', { text: c.reason }), el('td', { text: c.message || '' }), el('td', { text: age(c.lastTransitionTime) })),
      ),
    );
    const since = new Date(Date.now() - 3600e3).toISOString();
    if (S.access && S.access.allowed.getTelemetry) {
      const series = await Promise.all(CHARTS.map(([metric]) => listAll(base + '/telemetry', { metric, since })));
      charts.replaceChildren(...CHARTS.map(([metric, title, max], i) => chart(metric, title, max, series[i].items)));
    } else {
      charts.replaceChildren(el('p', { class: 'muted', text: 'RBAC does not allow you get robots/telemetry here.' }));
    }
    if (S.access && S.access.allowed.getEvents) {
      const { items } = await listAll(base + '/events', { since });
      events.replaceChildren(
        ...items.slice(-50).reverse().map((e) =>
          el('tr', { 'data-seq': e.seq }, el('td', { class: 'time', text: dateTime(e.ts_ms) }), el('td', { class: 'sev-' + e.severity, text: e.severity }), el('td', { text: e.kind }), el('td', { text: e.message })),
        ),
      );
    } else {
      events.replaceChildren(el('tr', {}, el('td', { colspan: 4, class: 'muted', text: 'RBAC does not allow you get robots/events here.' })));
    }
  };
  return { setup };
}

/** An SVG line chart of `samples` over the last hour. */
function chart(metric, title, fixedMax, samples) {
  const W = 360, H = 140, PAD = 28;
  const NS = 'http://www.w3.org/2000/svg';
  const svg = document.createElementNS(NS, 'svg');
  svg.setAttribute('width', W);
  svg.setAttribute('height', H);
  svg.setAttribute('data-metric', metric);
  svg.setAttribute('data-samples', samples.length);
  const add = (tag, attrs, text) => {
    const e = document.createElementNS(NS, tag);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (text !== undefined) e.textContent = text;
    svg.append(e);
  };
  const now = Date.now();
  // The last hour, or less when the data is younger: a robot that just connected gets a chart
  // of its first minutes, not a dot at the right edge.
  const t0 = Math.max(now - 3600e3, (samples.length ? samples[0].ts_ms : now) - 10e3);
  const span = now - t0;
  const max = fixedMax || Math.max(1, ...samples.map((s) => s.value)) * 1.1;
  const x = (t) => PAD + ((t - t0) / span) * (W - PAD - 6);
  const y = (v) => H - 16 - (Math.min(v, max) / max) * (H - 30);
  add('line', { x1: PAD, y1: y(0), x2: W - 6, y2: y(0), stroke: '#cbd5e1' });
  add('line', { x1: PAD, y1: y(max), x2: W - 6, y2: y(max), stroke: '#eef2f7' });
  add('text', { x: 2, y: y(max) + 4, 'font-size': 10, fill: '#6b7280' }, max.toFixed(0));
  add('text', { x: 2, y: y(0) + 4, 'font-size': 10, fill: '#6b7280' }, '0');
  add('text', { x: PAD, y: H - 2, 'font-size': 10, fill: '#6b7280' }, '−' + (span >= 120e3 ? Math.round(span / 60e3) + ' min' : Math.round(span / 1e3) + ' s'));
  add('text', { x: W - 30, y: H - 2, 'font-size': 10, fill: '#6b7280' }, 'now');
  if (samples.length) {
    const points = samples.map((s) => x(s.ts_ms).toFixed(1) + ',' + y(s.value).toFixed(1)).join(' ');
    add('polyline', { points, fill: 'none', stroke: '#2563eb', 'stroke-width': 1.5 });
    const end = samples[samples.length - 1];
    add('circle', { cx: x(end.ts_ms), cy: y(end.value), r: 2.5, fill: '#2563eb' });
  }
  const last = samples.length ? samples[samples.length - 1].value.toFixed(1) : 'no data';
  return el('div', { class: 'chart' }, el('div', { class: 'title', text: title + ' · ' + last }), svg);
}

// ---------------------------------------------------------------- rollouts

function rolloutsView() {
  let list;
  const setup = (root) => {
    list = el('div', { id: 'rollouts' });
    const legend = el('p', { class: 'legend muted' }, 'Per batch:', STATES.map((s) => [el('span', { class: 's-' + s }), s]));
    root.append(el('h2', { text: 'Rollouts' }), legend, list);
    return refresh;
  };
  const refresh = async () => {
    const { items } = await listAll('/api/v1/namespaces/' + ns() + '/rollouts', {});
    list.replaceChildren(...(items.length ? items.map((d) => rolloutCard(d, refresh)) : [el('p', { class: 'muted', text: 'No RobotDeployments in ' + S.ns + '.' })]));
  };
  const subscription = {
    query: 'subscription ($ns: String!) { rolloutProgress(namespace: $ns) { name } }',
    variables: { ns: S.ns },
  };
  return { setup, subscription };
}

function rolloutCard(d, refresh) {
  const name = d.metadata.name;
  const st = d.status || {};
  const allowed = S.access && S.access.allowed.patchRollouts;
  const why = allowed ? null : 'RBAC does not allow you patch robotdeployments in ' + S.ns;
  const act = (action, label, confirmation) =>
    el('button', {
      type: 'button',
      'data-action': action,
      disabled: !allowed,
      title: why,
      text: label,
      onclick: async (e) => {
        if (confirmation && !(await confirmAction(...confirmation))) return;
        e.target.disabled = true;
        try {
          await api('/api/v1/namespaces/' + ns() + '/rollouts/' + encodeURIComponent(name) + '/' + action, 'POST');
          setStatus(label + ' ' + name + ': done');
          await refresh();
        } catch (err) {
          setStatus(label + ' ' + name + ': ' + err.message, true);
          e.target.disabled = false;
        }
      },
    });
  const batches = new Map();
  for (const r of st.robots || []) {
    if (!batches.has(r.batch)) batches.set(r.batch, []);
    batches.get(r.batch).push(r);
  }
  const canary = (d.spec.strategy && d.spec.strategy.canary) || 0;
  const last = Math.max(st.totalBatches || 0, ...[...batches.keys()].map((b) => b + 1));
  const bars = [];
  for (let b = 0; b < last; b++) bars.push(batchBar(b, batches.get(b) || [], canary));
  const failed = (st.robots || []).filter((r) => r.state === 'Failed' || r.state === 'RolledBack');
  return el(
    'div',
    { class: 'rollout', 'data-rollout': name, 'data-phase': st.phase || 'Pending' },
    el(
      'div',
      { class: 'head' },
      el('strong', { text: name }),
      el('span', { class: 'badge phase-' + rolloutColour(st.phase), text: st.phase || 'Pending' }),
      // A pause outlives the phase it was set in (a Completed rollout still picks up robots
      // selected later, and a paused one does not): say so beside the phase.
      d.spec.paused && st.phase !== 'Paused' ? el('span', { class: 'badge phase-Unknown', 'data-paused': '', text: 'Paused' }) : null,
      el('span', { text: d.spec.agent && !d.spec.release ? 'agent ' + d.spec.agent.version : 'release ' + ((d.spec.release && d.spec.release.version) || '?') }),
      el('span', { class: 'muted', text: (st.progress || '') + (st.totalBatches ? ' · batch ' + (st.currentBatch || 0) + '/' + st.totalBatches : '') }),
      el('span', { class: 'actions' }, d.spec.paused ? act('resume', 'Resume') : act('pause', 'Pause'), act('undo', 'Undo', undoConfirmation(d))),
    ),
    st.message ? el('p', { class: 'muted', text: st.message }) : null,
    bars,
    failed.length
      ? el('div', { class: 'failed' }, el('h3', { text: 'Failed or rolled back' }), el('ul', {}, failed.map((r) => el('li', { 'data-failed': r.robot }, el('strong', { text: r.robot }), ' (' + r.state + '): ' + (r.message || 'no message')))))
      : null,
  );
}

/** What the undo dialog says for rollout `d`: title, text, the confirming button's label. */
function undoConfirmation(d) {
  const st = d.status || {};
  const updated = (st.robots || []).filter((r) => r.state === 'Updated').length;
  const release = d.spec.agent && !d.spec.release ? 'agent ' + d.spec.agent.version : 'release ' + ((d.spec.release && d.spec.release.version) || '?');
  return [
    'Undo rollout ' + d.metadata.name + '?',
    'Every robot it updated to ' + release + ' (' + updated + ' so far) goes back to the release it ran before, robots still downloading stop, and the rollout ends RolledBack.',
    'Undo ' + d.metadata.name,
  ];
}

/** Asks before an action: a modal dialog; resolves to whether the user confirmed. */
function confirmAction(title, text, ok) {
  const dialog = $('confirm');
  $('confirm-title').textContent = title;
  $('confirm-text').textContent = text;
  $('confirm-ok').textContent = ok;
  dialog.returnValue = '';
  dialog.showModal();
  $('confirm-cancel').focus();
  return new Promise((resolve) => dialog.addEventListener('close', () => resolve(dialog.returnValue === 'ok'), { once: true }));
}

function rolloutColour(phase) {
  if (phase === 'Completed') return 'Online';
  if (phase === 'Progressing') return 'Progressing';
  if (phase === 'Failed' || phase === 'RollingBack' || phase === 'RolledBack') return 'Offline';
  if (phase === 'Paused' || phase === 'Aborted') return 'Unknown';
  return 'Pending';
}

function batchBar(batch, robots, canary) {
  const counts = {};
  for (const r of robots) counts[r.state] = (counts[r.state] || 0) + 1;
  const bar = el('div', { class: 'bar' });
  for (const s of STATES) {
    if (!counts[s]) continue;
    const part = el('span', { class: 's-' + s, title: counts[s] + ' ' + s });
    part.style.width = (100 * counts[s]) / robots.length + '%';
    bar.append(part);
  }
  const text = robots.length ? STATES.filter((s) => counts[s]).map((s) => counts[s] + ' ' + s.toLowerCase()).join(', ') : 'not started';
  return el('div', { class: 'batch', 'data-batch': batch, 'data-updated': counts.Updated || 0, 'data-total': robots.length }, el('span', { class: 'name', text: canary > 0 ? (batch === 0 ? 'canary' : 'batch ' + batch) : 'batch ' + (batch + 1) }), bar, el('span', { class: 'muted', text }));
}

// ---------------------------------------------------------------- start

window.addEventListener('DOMContentLoaded', () => {
  $('login-form').addEventListener('submit', login);
  $('confirm-ok').addEventListener('click', () => $('confirm').close('ok'));
  $('confirm-cancel').addEventListener('click', () => $('confirm').close('cancel'));
  $('logout').addEventListener('click', () => logout('Logged out.'));
  $('namespace').addEventListener('change', changeNamespace);
  window.addEventListener('hashchange', () => S.token && render());
  if (!S.token) return logout();
  loadAccess()
    .then(() => {
      $('nav').hidden = false;
      $('namespace').value = S.ns;
      render();
    })
    .catch((e) => logout(e.message));
});
