// The page's panels around the 3-D view: per-view pictures, the run's summary and scores, the
// match pictures.

export function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === 'class') e.className = v;
    else if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

export function fmt(v) {
  if (typeof v === 'number') return Number.isInteger(v) ? v.toLocaleString() : String(Number(v.toPrecision(3)));
  if (Array.isArray(v)) return v.map(fmt).join(', ');
  if (v === null || v === undefined) return '-';
  if (typeof v === 'object') return Object.entries(v).map(([k, x]) => `${k} ${fmt(x)}`).join(', ');
  return String(v);
}

export function buildGallery(data, lookFrom) {
  const tabs = document.getElementById('tabs');
  const strip = document.getElementById('gallery');
  const kinds = ['photo', 'depth', 'normals', 'conf'].filter((k) => data.views.some((v) => v.pictures && v.pictures[k]));
  const labels = { photo: 'photos', depth: 'depth', normals: 'normals', conf: 'confidence' };
  function show(kind) {
    for (const b of tabs.children) b.classList.toggle('active', b.dataset.kind === kind);
    strip.replaceChildren(
      ...data.views.map((v, k) => {
        const src = v.pictures && v.pictures[kind];
        return el(
          'figure',
          { class: 'card', title: `${v.name}: click to look from this camera`, onclick: () => lookFrom(k) },
          src ? el('img', { src, alt: `${v.name} ${labels[kind]}`, loading: 'lazy' }) : el('div', { class: 'none' }, 'none'),
          el('figcaption', {}, v.name),
        );
      }),
    );
  }
  for (const k of kinds) tabs.append(el('button', { 'data-kind': k, onclick: () => show(k) }, labels[k]));
  if (kinds.length) show(kinds[0]);
}

export function buildSummary(data) {
  const table = document.getElementById('summary');
  const rows = [];
  const add = (k, v) => rows.push(el('tr', {}, el('th', {}, k), el('td', {}, fmt(v))));
  const s = data.summary || {};
  const first = ['photos', 'registered', 'cameras', 'focals_px', 'reprojection_rms_px', 'points', 'mesh_triangles', 'network_runs', 'cache_hits'];
  const keys = first.filter((k) => k in s).concat(Object.keys(s).filter((k) => !first.includes(k)));
  for (const k of keys) {
    if (['warnings', 'unregistered', 'graph', 'seconds'].includes(k)) continue;
    add(k.replaceAll('_', ' ').replace(/ px$/, ' (px)'), s[k]);
  }
  if (s.graph) add('pair graph', `${s.graph.name}, ${s.graph.pairs} pairs`);
  if (s.unregistered && s.unregistered.length) add('not registered', s.unregistered.join(', '));
  if (s.seconds) {
    const total = Object.values(s.seconds).reduce((a, b) => a + (b || 0), 0);
    add('seconds', Object.entries(s.seconds).filter(([, t]) => t >= 0.05).map(([k, t]) => `${k} ${t.toFixed(1)}`).join(', ') + ` (${total.toFixed(1)} in all)`);
  }
  table.replaceChildren(...rows);
  const warn = document.getElementById('warnings');
  warn.replaceChildren(...(s.warnings || []).map((w) => el('li', {}, w)));
  const scores = document.getElementById('scores');
  // Added by `dens3r eval` (viewer/scores.js): one table per kind of score.
  const all = window.DENS3R_SCORES || {};
  scores.replaceChildren(
    ...Object.entries(all).flatMap(([kind, s]) => [
      el('h2', {}, `scores: ${kind}`),
      el('table', {}, ...Object.entries(s).map(([k, v]) => el('tr', {}, el('th', {}, k.replaceAll('_', ' ')), el('td', {}, fmt(v))))),
    ]),
  );
}

export function buildMatches(data) {
  const box = document.getElementById('matches');
  if (!data.matches || !data.matches.length) return;
  const light = document.getElementById('lightbox');
  const big = light.querySelector('img');
  light.addEventListener('click', () => light.classList.remove('open'));
  box.replaceChildren(
    el('h2', {}, `match pictures (${data.matches.length})`),
    ...data.matches.map((m) =>
      el(
        'img',
        {
          src: m.path,
          alt: `${m.a} - ${m.b}`,
          title: `${m.a} - ${m.b}: click to enlarge`,
          loading: 'lazy',
          onclick: () => {
            big.src = m.path;
            light.classList.add('open');
          },
        },
      ),
    ),
  );
}
