// The ground station's map page: per drone the growing ortho (XYZ tiles) over the offline base map, the
// drone's live position and GNSS track, the keyframe track, the coverage gaps, the targets coloured by residual, and the go / no-go panel. The server pushes
// the status over a WebSocket (/ws) whenever it changes; the layers are fetched when their version changes.
// Every string that came from a drone or a file is put on the page as text (textContent, or escaped for
// Leaflet's tooltips), never as HTML.
'use strict';
const map = L.map('map', {zoomControl: true, maxZoom: 23});
map.setView([0, 0], 2);
L.control.scale({imperial: false}).addTo(map);
const layers = {};   // drone key -> {ortho, coverage, track, targets, live, zoom, fitted, versions}
let limits = {};
let basemap = null;  // the base map's Leaflet layer, once the server says it has one
let viewFitted = false;
let lastStatus = null, lastPushMs = 0, socketOpen = false;
let clockOffsetMs = 0;   // this browser's clock minus the station's (ages are on the station's clock)

function fmt(v, unit, digits) {   // v in metres (shown in cm), a share (shown in %), or as it is
  if (typeof v !== 'number' || !Number.isFinite(v)) return '–';
  const scale = unit === '%' || unit === 'cm' ? 100 : 1;
  return (scale * v).toFixed(digits ?? 1) + ' ' + unit;
}

// A name for a one-line tooltip: at most 80 characters (the panel shows names in full).
function short(t) {
  const a = Array.from(String(t));
  return a.length > 80 ? a.slice(0, 79).join('') + '…' : a.join('');
}

// A line of the panel from a drone or a file: cut to 200 characters, the whole text in its tooltip (title).
function clip(t) {
  const a = Array.from(String(t));
  return a.length > 200 ? el('span', {title: String(t)}, a.slice(0, 199).join('') + '…') : String(t);
}

function escapeHTML(t) {
  return String(t).replace(/[&<>"']/g, c => ({'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;'})[c]);
}

// el('td', {className: 'v'}, 'text', child, ...): an element whose strings are text nodes.
function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === 'dataset') Object.assign(e.dataset, v); else e.setAttribute(k === 'className' ? 'class' : k, String(v));
  }
  for (const c of children.flat()) if (c !== null && c !== undefined) e.append(c instanceof Node ? c : String(c));
  return e;
}

const safeKey = k => encodeURIComponent(String(k));

function targetColour(p) {
  if (p.role === 'gcp') return '#2f81f7';
  const lim = limits.max_check_rmse_h_m || 0.05;
  return p.residual_h_m <= lim / 2 ? '#1a7f37' : p.residual_h_m <= lim ? '#d4a72c' : '#cf222e';
}

function cm(v) { return typeof v === 'number' && Number.isFinite(v) ? (100 * v).toFixed(1) + ' cm' : '–'; }

function ensureLayers(key, zoom) {
  let l = layers[key];
  if (!l) {
    l = layers[key] = {
      coverage: L.geoJSON(null, {style: f => f.properties.role === 'gap'
          ? {color: '#ff003c', weight: 2, fillOpacity: 0.45}
          : {color: '#2f81f7', weight: 1.5, dashArray: '6 4', fill: false},
        onEachFeature: (f, lay) => f.properties.role === 'gap' &&
          lay.bindTooltip(escapeHTML(`${short(f.properties.kind)} gap ${f.properties.area_m2} m²`))}).addTo(map),
      track: L.geoJSON(null, {style: {color: '#ffd33d', weight: 2}}).addTo(map),
      // The drone where its GNSS puts it now, and the track its fixes drew (GET /drones/KEY/live.geojson).
      live: L.geoJSON(null, {style: {color: '#00e5ff', weight: 1.5, opacity: 0.8},
        pointToLayer: (f, ll) => L.circleMarker(ll, {radius: 8, weight: 3, color: '#fff', fillColor: '#ff3d00',
          fillOpacity: 1}).bindTooltip(escapeHTML(`${short(f.properties.drone)}: ` +
          `${Number(f.properties.h_m).toFixed(1)} m (fix status ${f.properties.status})`))}).addTo(map),
      targets: L.geoJSON(null, {pointToLayer: (f, ll) => L.circleMarker(ll, {radius: 7, weight: 2,
          color: f.properties.role === 'gcp' ? '#2f81f7' : '#fff', fillColor: targetColour(f.properties),
          fillOpacity: f.properties.role === 'gcp' ? 0.1 : 0.95}).bindTooltip(escapeHTML(
          `${short(f.properties.name)}: ${cm(f.properties.residual_h_m)} H, ${cm(f.properties.residual_v_m)} V`))}).addTo(map),
      ortho: null, zoom: null, fitted: false, versions: {}};
  }
  if (Number.isInteger(zoom) && l.zoom !== zoom) {
    if (l.ortho) map.removeLayer(l.ortho);
    l.zoom = zoom;
    // Tiles exist at one zoom only: shown scaled within 4 levels of it (further out a view would ask for
    // thousands of tiles).
    l.ortho = L.tileLayer(`/tiles/${safeKey(key)}/{z}/{x}/{y}.png?v={v}`, {v: Date.now(), minNativeZoom: zoom,
      maxNativeZoom: zoom, maxZoom: 23, minZoom: zoom - 4, tileSize: 256});
    l.ortho.addTo(map);
    if (basemap) basemap.bringToBack();
  }
  return l;
}

function setBasemap(info) {
  if (!info || basemap) return;
  // Shown from 2 levels below its coarsest tiles (scaled), like the ortho: further out it would ask for
  // thousands of its finest tiles.
  basemap = L.tileLayer('/basemap/{z}/{x}/{y}', {minZoom: Math.max(0, info.minzoom - 2), maxZoom: 23,
    maxNativeZoom: info.maxzoom, minNativeZoom: info.minzoom, attribution: escapeHTML(info.attribution || info.name || '')}).addTo(map);
  basemap.bringToBack();
  document.getElementById('basemap').textContent = `base map: ${info.name} (${info.kind}, zoom ${info.minzoom}–${info.maxzoom})`;
  if (!viewFitted && Array.isArray(info.bounds) && info.bounds.length === 4) {
    const [w, s, e, n] = info.bounds;
    map.fitBounds([[s, w], [n, e]]);
  }
}

async function getJSON(url) {
  const r = await fetch(url, {cache: 'no-store', credentials: 'same-origin'});
  return r.ok ? r.json() : null;
}

function check(g, name) { return (g.checks || []).find(c => c.name.startsWith(name)); }

function statusWord(c) {   // a figure's state for the table: provisional / not measured / inconclusive
  if (!c || c.state === 'GO' || c.state === 'NO-GO') return '';
  return c.value === null ? ' (not measured)' : c.status === 'provisional' ? ' (provisional)' : ' (wait)';
}

// The drone's latest fix: where it is, how old, and how many points its track on the map has.
function livePosition(p) {
  if (!p || !Number.isFinite(p.lat_deg) || !Number.isFinite(p.lon_deg)) return 'no fix yet';
  const ns = p.lat_deg >= 0 ? 'N' : 'S', ew = p.lon_deg >= 0 ? 'E' : 'W';
  return `${Math.abs(p.lat_deg).toFixed(6)}° ${ns} ${Math.abs(p.lon_deg).toFixed(6)}° ${ew}, ` +
    `${Number(p.h_m).toFixed(1)} m, ${Number(p.age_s).toFixed(0)} s ago, track ${p.track_points ?? 0} points`;
}

function panel(key, d) {
  const g = d.go_no_go || {verdict: 'WAIT', reasons: [], checks: []};
  const c = d.coverage || {}, a = d.accuracy || {};
  const fs = a.fix_share || {};
  const gcp = a.gcp_rmse || {};
  const chH = check(g, 'check points horizontal');
  const rows = [
    ['check points H RMSE', `${fmt(a.check_rmse_h_m, 'cm')} (${a.check_count ?? 0})${statusWord(chH)}`],
    ['check points V RMSE', fmt(a.check_rmse_v_m, 'cm')],
    ['block georeference', a.georeference ?? '–'],
    ['GCP residuals H / V', gcp.count ? `${fmt(gcp.horizontal_m, 'cm')} / ${fmt(gcp.vertical_m, 'cm')} (${gcp.count})` : '–'],
    ['coverage', fmt(c.coverage_share, '%')],
    ['gaps (all kinds)', `${(c.gap_list || []).length}, largest ${fmt(check(g, 'largest gap')?.value, 'm²', 0)}`],
    ['forward / side overlap', `${fmt(c.forward_overlap_median, '%', 0)} / ${fmt(c.side_overlap_min, '%', 0)}`],
    ['RTK fixed / float / 3D', `${fmt(fs.rtk_fixed, '%', 0)} / ${fmt(fs.rtk_float, '%', 0)} / ${fmt(fs['3d'], '%', 0)}`],
    ['GNSS bias estimate E N U', Array.isArray(a.gnss_bias_enu_m) ? a.gnss_bias_enu_m.map(v => (100 * Number(v)).toFixed(1)).join(' ') + ' cm' : '–'],
    ['keyframes / ortho tiles', `${d.keyframes} / ${(d.ortho || {}).tiles}`],
    ['position (GNSS)', livePosition(d.position)],
  ];
  const ctl = a.control;
  if (ctl) rows.splice(4, 0, ['GCPs used / horizontally / not / held',
    `${ctl.gcps_full} / ${ctl.gcps_horizontal_only} / ${ctl.gcps_rejected} / ${ctl.gcps_held} of ${ctl.gcps}`]);
  const verdict = ['GO', 'NO-GO', 'WAIT'].includes(g.verdict) ? g.verdict : 'WAIT';
  const box = el('div', {className: 'drone', id: `drone-${key}`},
    el('h2', {}, clip(d.ns), ' ', el('span', {className: `verdict ${verdict}`, id: `verdict-${key}`}, verdict),
      (g.warnings || []).length ? el('span', {className: 'verdict WARN'}, `WARN ${g.warnings.length}`) : null),
    (g.reasons || []).map(r => el('div', {className: 'reason'}, clip(r))),
    (g.warnings || []).map(w => el('div', {className: 'warn'}, 'WARN: ', w)),
    Object.entries(d.health || {}).filter(([, h]) => Array.isArray(h) && h[0] === 1).map(([n, h]) =>
      el('div', {className: 'warn'}, `${n.replace(/^\//, '')} WARN: `, clip(h[1]))),
    (ctl && Array.isArray(ctl.faults) ? ctl.faults : []).map(f => el('div', {className: 'reason'}, 'control: ',
      clip(f))),
    Object.entries(d.unknown_publishers || {}).map(([t, who]) => el('div', {className: 'unknown'},
      `${t}: unknown publisher ${[].concat(who).join(', ')}, not counted (${(d.not_counted || {})[t] ?? 0} messages)`)),
    el('table', {}, rows.map(([k, v]) => el('tr', {}, el('td', {}, k), el('td', {className: 'v'}, v)))));
  const gaps = c.gap_list || [];
  if (gaps.length) box.append(el('h2', {}, 'Gaps'), el('table', {}, gaps.map(x =>
    el('tr', {}, el('td', {}, x.kind), el('td', {className: 'v'}, `${x.area_m2} m²`)))));
  box.append(el('div', {},
    el('a', {href: `/drones/${safeKey(key)}/refly.plan`, download: `${key}_refly.plan`}, 're-fly plan (.plan)'), ' · ',
    el('a', {href: `/drones/${safeKey(key)}/coverage.geojson`, download: `${key}_gaps.geojson`}, 'gaps (GeoJSON)')));
  return box;
}

async function refreshLayers(key, d) {
  const l = ensureLayers(key, null);
  const v = d.versions || {};
  const kinds = ['coverage', 'track', 'targets', 'live'].filter(k => l.versions[k] !== v[k]);
  const docs = await Promise.all(kinds.map(k => getJSON(`/drones/${safeKey(key)}/${k}.geojson`)));
  kinds.forEach((k, i) => { l[k].clearLayers(); if (docs[i]) l[k].addData(docs[i]); l.versions[k] = v[k]; });
  const b = L.featureGroup([l.coverage, l.track, l.targets, l.live]).getBounds();
  if (!l.fitted && b.isValid()) {   // the view fits the drones on their first data
    const all = L.latLngBounds([]);
    for (const x of Object.values(layers)) {
      const bx = L.featureGroup([x.coverage, x.track, x.targets, x.live]).getBounds();
      if (bx.isValid()) all.extend(bx);
    }
    map.fitBounds(all.pad(0.2), {maxZoom: 20});
    l.fitted = viewFitted = true;
  }
  if (l.fitted && d.ortho) ensureLayers(key, d.ortho.zoom);   // the tiles once the view is on the drone
}

function showUnknown(st) {
  const box = document.getElementById('unknown');
  box.replaceChildren();
  for (const [ns, topics] of Object.entries(st.unknown_drones || {})) {
    box.append(el('div', {className: 'unknown'}, `unknown drone ${ns} (not counted): `,
      Object.entries(topics).map(([t, who]) => `${t} from ${[].concat(who).join(', ')}`).join('; ')));
  }
  if ((st.diagnostics_unknown_publishers || []).length) {
    box.append(el('div', {className: 'unknown'}, '/diagnostics also from ',
      st.diagnostics_unknown_publishers.join(', '), ': drone health not counted'));
  }
  // Whether the drones' DDS traffic is authenticated and encrypted, at the top of the panel; why, below it.
  const sec = st.security || {};
  const box2 = document.getElementById('security');
  box2.replaceChildren(el('b', {}, sec.headline || 'DDS security: not known'),
    sec.summary ? el('details', {}, el('summary', {}, 'ROS 2 security'), sec.summary) : null);
  box2.className = sec.enabled ? 'secure' : 'insecure';
}

async function apply(msg) {
  const st = msg.status;
  lastStatus = st;
  lastPushMs = Date.now();
  if (typeof msg.server_time_unix_s === 'number') clockOffsetMs = lastPushMs - 1000 * msg.server_time_unix_s;
  limits = st.limits || {};
  setBasemap(st.basemap);
  const boxes = [];
  for (const [key, d] of Object.entries(st.drones || {})) {
    await refreshLayers(key, d);
    const l = layers[key];
    const changed = (msg.tiles || {})[key] || [];
    if (l.ortho && changed.length) l.ortho.setUrl(`/tiles/${safeKey(key)}/{z}/{x}/{y}.png?v=${Date.now()}`);
    boxes.push(panel(key, d));
  }
  const drones = document.getElementById('drones');
  if (boxes.length) drones.replaceChildren(...boxes); else drones.textContent = 'waiting for drones…';
  showUnknown(st);
  document.body.dataset.updated = String(Date.now());
  showUpdated();
}

function showUpdated() {   // when the figures were last updated, and whether the push is alive
  const e = document.getElementById('updated');
  if (!lastStatus) { e.textContent = socketOpen ? 'connected, no status yet' : 'not connected'; return; }
  const times = Object.values(lastStatus.drones || {}).map(d => d.updated_unix_s).filter(t => typeof t === 'number');
  const data = times.length ? new Date(1000 * Math.max(...times) + clockOffsetMs) : null;   // browser time
  const age = data ? Math.round((Date.now() - data.getTime()) / 1000) : null;
  e.textContent = (data ? `drone data ${data.toLocaleTimeString()} (${age} s ago)` : 'no drone data yet') +
    ` · status ${new Date(lastPushMs).toLocaleTimeString()}` + (socketOpen ? '' : ' · DISCONNECTED, retrying');
  e.className = !socketOpen || (age !== null && age > 15) ? 'stale' : '';
}
setInterval(showUpdated, 1000);

let queue = Promise.resolve();
function connect() {
  const ws = new WebSocket(`${location.protocol === 'https:' ? 'wss' : 'ws'}://${location.host}/ws`);
  ws.onopen = () => { socketOpen = true; showUpdated(); };
  ws.onmessage = ev => {
    let msg;
    try { msg = JSON.parse(ev.data); } catch (e) { return; }
    if (msg.type === 'status') queue = queue.then(() => apply(msg)).catch(e => {
      document.getElementById('drones').textContent = 'status not shown: ' + e;
    });
  };
  ws.onclose = () => { socketOpen = false; showUpdated(); setTimeout(connect, 2000); };
}
connect();
