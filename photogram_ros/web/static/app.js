// The ground station's map page: per drone the growing ortho (XYZ tiles), the track, the coverage gaps,
// the targets coloured by residual, and the go / no-go panel; refreshed from /status.json.
'use strict';
const map = L.map('map', {zoomControl: true, maxZoom: 23});
map.setView([0, 0], 2);
L.control.scale({imperial: false}).addTo(map);
const layers = {};   // drone key -> {ortho, coverage, track, targets, zoom, fitted}
let limits = {};

function fmt(v, unit, digits) {   // v in metres (shown in cm), a share (shown in %), or as it is
  if (v === null || v === undefined || Number.isNaN(v)) return '–';
  const scale = unit === '%' || unit === 'cm' ? 100 : 1;
  return (scale * v).toFixed(digits ?? 1) + ' ' + unit;
}

function escapeHTML(t) {
  return String(t).replace(/[&<>"']/g, c => ({'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;'})[c]);
}

function targetColour(p) {
  if (p.role === 'gcp') return '#2f81f7';
  const lim = limits.max_check_rmse_h_m || 0.05;
  return p.residual_h_m <= lim / 2 ? '#1a7f37' : p.residual_h_m <= lim ? '#d4a72c' : '#cf222e';
}

function ensureLayers(key, zoom) {
  let l = layers[key];
  if (!l) {
    l = layers[key] = {
      coverage: L.geoJSON(null, {style: f => f.properties.role === 'gap'
          ? {color: '#ff003c', weight: 2, fillOpacity: 0.45}
          : {color: '#2f81f7', weight: 1.5, dashArray: '6 4', fill: false},
        onEachFeature: (f, lay) => f.properties.role === 'gap' &&
          lay.bindTooltip(`${f.properties.kind} gap ${f.properties.area_m2} m²`)}).addTo(map),
      track: L.geoJSON(null, {style: {color: '#ffd33d', weight: 2}}).addTo(map),
      targets: L.geoJSON(null, {pointToLayer: (f, ll) => L.circleMarker(ll, {radius: 7, weight: 2,
          color: f.properties.role === 'gcp' ? '#2f81f7' : '#fff', fillColor: targetColour(f.properties),
          fillOpacity: f.properties.role === 'gcp' ? 0.1 : 0.95}).bindTooltip(
          `${f.properties.name}: ${(100 * f.properties.residual_h_m).toFixed(1)} cm H, ` +
          `${(100 * f.properties.residual_v_m).toFixed(1)} cm V`)}).addTo(map),
      ortho: null, zoom: null, version: 0, fitted: false};
  }
  if (zoom !== null && l.zoom !== zoom) {
    if (l.ortho) map.removeLayer(l.ortho);
    l.zoom = zoom;
    // Tiles exist at one zoom only: shown scaled within 4 levels of it (further out a view would ask for
    // thousands of tiles).
    l.ortho = L.tileLayer(`/tiles/${key}/{z}/{x}/{y}.png?v={v}`, {v: 0, minNativeZoom: zoom, maxNativeZoom: zoom,
                                                                      maxZoom: 23, minZoom: zoom - 4, tileSize: 256});
    l.ortho.addTo(map);
    l.ortho.bringToBack();
  }
  return l;
}

async function getJSON(url) {
  const r = await fetch(url, {cache: 'no-store'});
  return r.ok ? r.json() : null;
}

function panel(key, d) {
  const g = d.go_no_go, c = d.coverage || {}, a = d.accuracy || {};
  const fs = a.fix_share || {};
  const rows = [
    ['check points H RMSE', fmt(a.check_rmse_h_m, 'cm') + ` (${a.check_count ?? 0})`],
    ['check points V RMSE', fmt(a.check_rmse_v_m, 'cm')],
    ['GCP residuals H / V', a.gcp_rmse && a.gcp_rmse.count ? `${fmt(a.gcp_rmse.horizontal_m, 'cm')} / ` +
      `${fmt(a.gcp_rmse.vertical_m, 'cm')} (${a.gcp_rmse.count})` : '–'],
    ['coverage', fmt(c.coverage_share, '%')],
    ['gaps', `${(c.gap_list || []).length}, largest ${fmt(c.largest_gap_m2, 'm²', 0)}`],
    ['forward / side overlap', `${fmt(c.forward_overlap_median, '%', 0)} / ${fmt(c.side_overlap_min, '%', 0)}`],
    ['RTK fixed / float / 3D', `${fmt(fs.rtk_fixed, '%', 0)} / ${fmt(fs.rtk_float, '%', 0)} / ${fmt(fs['3d'], '%', 0)}`],
    ['GNSS bias E N U', a.gnss_bias_enu_m ? a.gnss_bias_enu_m.map(v => (100 * v).toFixed(1)).join(' ') + ' cm' : '–'],
    ['keyframes / ortho tiles', `${d.keyframes} / ${d.ortho.tiles}`],
  ];
  const ctl = a.control;
  if (ctl) rows.splice(3, 0, ['GCPs used / horizontally / not / held',
    `${ctl.gcps_full} / ${ctl.gcps_horizontal_only} / ${ctl.gcps_rejected} / ${ctl.gcps_held} of ${ctl.gcps}`]);
  const faults = ctl ? ctl.faults.map(f => `<div class="reason">control: ${escapeHTML(f)}</div>`).join('') : '';
  const gaps = (c.gap_list || []).map(x => `<tr><td>${x.kind}</td><td class="v">${x.area_m2} m²</td></tr>`).join('');
  return `<h2>${d.ns} <span class="verdict ${g.verdict}" id="verdict-${key}">${g.verdict}</span></h2>` +
    g.reasons.map(r => `<div class="reason">${r}</div>`).join('') + faults +
    '<table>' + rows.map(([k, v]) => `<tr><td>${k}</td><td class="v">${v}</td></tr>`).join('') + '</table>' +
    (gaps ? '<h2>Gaps</h2><table>' + gaps + '</table>' : '') +
    `<div><a href="/drones/${key}/refly.plan" download="${key}_refly.plan">re-fly plan (.plan)</a> · ` +
    `<a href="/drones/${key}/coverage.geojson" download="${key}_gaps.geojson">gaps (GeoJSON)</a></div>`;
}

async function refresh() {
  try {
    const st = await getJSON('/status.json');
    if (!st) return;
    limits = st.limits || {};
    const html = [];
    for (const [key, d] of Object.entries(st.drones)) {
      const l = ensureLayers(key, null);
      const [cov, track, targets] = await Promise.all(['coverage', 'track', 'targets'].map(
        k => getJSON(`/drones/${key}/${k}.geojson`)));
      l.coverage.clearLayers(); if (cov) l.coverage.addData(cov);
      l.track.clearLayers(); if (track) l.track.addData(track);
      l.targets.clearLayers(); if (targets) l.targets.addData(targets);
      const b = L.featureGroup([l.coverage, l.track]).getBounds();
      if (!l.fitted && b.isValid()) { map.fitBounds(b.pad(0.1)); l.fitted = true; }
      if (l.fitted) ensureLayers(key, d.ortho.zoom);   // the tiles once the view is on the drone
      if (l.ortho && d.ortho.tiles !== l.version) { l.version = d.ortho.tiles; l.ortho.setUrl(
        `/tiles/${key}/{z}/{x}/{y}.png?v=${Date.now()}`); }
      html.push(panel(key, d));
    }
    document.getElementById('drones').innerHTML = html.join('') || 'waiting for drones…';
    document.body.dataset.updated = String(Date.now());
  } catch (e) {
    document.getElementById('drones').textContent = 'status not available: ' + e;
  }
}
refresh();
setInterval(refresh, 2000);
