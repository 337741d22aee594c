// The page dens3r writes beside a reconstruction (OUT/index.html): the point cloud and mesh,
// the cameras as frustums with their photos, a confidence slider, per-view pictures, match
// pictures and the run's summary. Its data is `window.DENS3R_SCENE`, set by viewer/scene.js
// (written by the `dens3r-viewer` crate); everything loads from the file system, no server.
//
// Conventions: the data is in dens3r's world frame (OpenCV: x right, y down, z forward,
// camera-to-world poses, row-major 4x4); the page turns the whole scene half a turn about x
// so that the first camera's up is the page's up.

import {
  BufferAttribute,
  BufferGeometry,
  Color,
  DoubleSide,
  Group,
  LineBasicMaterial,
  LineSegments,
  Matrix4,
  Mesh,
  MeshBasicMaterial,
  MeshNormalMaterial,
  PerspectiveCamera,
  PlaneGeometry,
  Points,
  PointsMaterial,
  Scene,
  SRGBColorSpace,
  Texture,
  Vector3,
  WebGLRenderer,
} from 'three';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';

const BACKGROUND = 0x1d2024;

/** Decodes base64 into a typed array of the given constructor. */
function decode(b64, Type) {
  const bin = atob(b64);
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return new Type(bytes.buffer);
}

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === 'class') e.className = v;
    else if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

function fmt(v) {
  if (typeof v === 'number') return Number.isInteger(v) ? v.toLocaleString() : String(Number(v.toPrecision(3)));
  if (Array.isArray(v)) return v.map(fmt).join(', ');
  if (v === null || v === undefined) return '-';
  if (typeof v === 'object') return Object.entries(v).map(([k, x]) => `${k} ${fmt(x)}`).join(', ');
  return String(v);
}

/** The point cloud, sorted by confidence (highest first), so a threshold is a draw range. */
function buildPoints(p) {
  const geo = new BufferGeometry();
  geo.setAttribute('position', new BufferAttribute(decode(p.positions, Float32Array), 3));
  geo.setAttribute('color', new BufferAttribute(decode(p.colors, Uint8Array), 3, true));
  const conf = decode(p.conf, Float32Array);
  const mat = new PointsMaterial({ size: p.point_size, vertexColors: true, sizeAttenuation: true });
  return { object: new Points(geo, mat), conf };
}

function buildMesh(m) {
  const geo = new BufferGeometry();
  geo.setAttribute('position', new BufferAttribute(decode(m.positions, Float32Array), 3));
  geo.setIndex(new BufferAttribute(decode(m.indices, Uint32Array), 1));
  let mat;
  if (m.colors) {
    geo.setAttribute('color', new BufferAttribute(decode(m.colors, Uint8Array), 3, true));
    mat = new MeshBasicMaterial({ vertexColors: true, side: DoubleSide });
  } else {
    geo.computeVertexNormals();
    mat = new MeshNormalMaterial({ side: DoubleSide });
  }
  return new Mesh(geo, mat);
}

/** A camera's frustum (apex to the image corners at `depth`) and its photo on the far plane. */
function buildFrustum(v, depth) {
  const m = new Matrix4().set(...v.c2w);
  const corner = (u, w) => new Vector3(((u - v.cx) / v.fx) * depth, ((w - v.cy) / v.fy) * depth, depth).applyMatrix4(m);
  const apex = new Vector3(0, 0, 0).applyMatrix4(m);
  const c = [corner(-0.5, -0.5), corner(v.width - 0.5, -0.5), corner(v.width - 0.5, v.height - 0.5), corner(-0.5, v.height - 0.5)];
  const pts = [];
  for (let i = 0; i < 4; i++) pts.push(apex, c[i], c[i], c[(i + 1) % 4]);
  const lines = new LineSegments(
    new BufferGeometry().setFromPoints(pts),
    new LineBasicMaterial({ color: 0xffb000 }),
  );
  const group = new Group();
  group.add(lines);
  if (v.thumb) {
    const img = new Image();
    const tex = new Texture(img);
    tex.colorSpace = SRGBColorSpace;
    img.onload = () => {
      tex.needsUpdate = true;
      requestRender();
    };
    img.src = v.thumb;
    // The plane spans the far rectangle: x along the image's rows, y down its columns.
    const w = c[0].distanceTo(c[1]);
    const h = c[0].distanceTo(c[3]);
    const plane = new Mesh(new PlaneGeometry(w, h), new MeshBasicMaterial({ map: tex, side: DoubleSide, transparent: true, opacity: 0.85 }));
    const centre = c[0].clone().add(c[2]).multiplyScalar(0.5);
    const x = c[1].clone().sub(c[0]).normalize();
    const y = c[0].clone().sub(c[3]).normalize(); // image up
    const z = new Vector3().crossVectors(x, y);
    plane.matrixAutoUpdate = false;
    plane.matrix.makeBasis(x, y, z).setPosition(centre);
    group.add(plane);
  }
  group.userData = { lines, apex, centre: c[0].clone().add(c[2]).multiplyScalar(0.5) };
  return group;
}

let requestRender = () => {};

function main() {
  const data = window.DENS3R_SCENE;
  const status = document.getElementById('status');
  if (!data) {
    status.textContent = 'viewer/scene.js did not load: keep index.html beside its viewer/ folder.';
    return;
  }
  document.title = `${data.title} - dens3r`;
  document.getElementById('title').textContent = data.title;

  const canvas = document.getElementById('view3d');
  const renderer = new WebGLRenderer({ canvas, antialias: true });
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setClearColor(new Color(BACKGROUND), 1);
  const scene = new Scene();
  const world = new Group();
  world.rotation.x = Math.PI; // OpenCV (y down, z forward) -> three.js (y up, z back)
  scene.add(world);

  const bounds = data.bounds;
  const radius = Math.max(bounds.radius, 1e-6);
  const camera = new PerspectiveCamera(55, 1, radius * 1e-3, radius * 100);
  const controls = new OrbitControls(camera, canvas);
  controls.addEventListener('change', () => requestRender());

  let points = null;
  if (data.points && data.points.count > 0) {
    points = buildPoints(data.points);
    world.add(points.object);
  }
  let mesh = null;
  if (data.mesh && data.mesh.triangles > 0) {
    mesh = buildMesh(data.mesh);
    world.add(mesh);
  }
  const frustums = new Group();
  const depth = data.frustum_depth || radius * 0.1;
  const views = data.views.map((v) => {
    const f = buildFrustum(v, depth);
    frustums.add(f);
    return f;
  });
  world.add(frustums);
  world.updateMatrixWorld(true);

  const toPage = (p) => p.clone().applyMatrix4(world.matrixWorld);
  const centre = toPage(new Vector3(...bounds.center));
  function lookFrom(k) {
    const f = views[k].userData;
    const eye = toPage(f.apex);
    const ahead = toPage(f.centre).sub(eye).normalize();
    // Step back behind the camera so its frustum and photo are in view.
    camera.position.copy(eye).addScaledVector(ahead, -depth * 2.5);
    controls.target.copy(eye).addScaledVector(ahead, radius * 0.8);
    controls.update();
    views.forEach((g, i) => g.userData.lines.material.color.set(i === k ? 0x30d0ff : 0xffb000));
    requestRender();
  }
  // Start with an overview: from beyond the first camera, raised, towards the scene's centre.
  function overview() {
    const up = new Vector3(0, 1, 0);
    const from = views.length ? toPage(views[0].userData.apex) : centre.clone().add(new Vector3(0, 0, radius));
    const dir = from.clone().sub(centre);
    if (dir.length() < radius * 0.5) dir.set(0, 0, 1);
    dir.normalize().multiplyScalar(radius * 2.2).addScaledVector(up, radius * 0.9);
    camera.position.copy(centre).add(dir);
    controls.target.copy(centre);
    controls.update();
    requestRender();
  }
  overview();
  document.getElementById('home').addEventListener('click', overview);

  // Rendering on demand.
  let pending = false;
  function render() {
    const w = canvas.clientWidth;
    const h = canvas.clientHeight;
    if (canvas.width !== Math.floor(w * renderer.getPixelRatio()) || canvas.height !== Math.floor(h * renderer.getPixelRatio())) {
      renderer.setSize(w, h, false);
      camera.aspect = w / Math.max(h, 1);
      camera.updateProjectionMatrix();
    }
    renderer.render(scene, camera);
  }
  requestRender = () => {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => {
      pending = false;
      render();
    });
  };
  window.addEventListener('resize', requestRender);

  // Controls: what is shown, the confidence threshold, the frustums.
  const mode = document.getElementById('mode');
  const modes = [];
  if (points) modes.push('points');
  if (mesh) modes.push('mesh');
  if (points && mesh) modes.push('both');
  for (const m of modes) mode.append(el('option', { value: m }, m));
  mode.value = mesh ? 'mesh' : 'points';
  const slider = document.getElementById('conf');
  const confLabel = document.getElementById('conf-label');
  function applyMode() {
    if (points) points.object.visible = mode.value !== 'mesh';
    if (mesh) mesh.visible = mode.value !== 'points';
    slider.disabled = !points;
    requestRender();
  }
  mode.addEventListener('change', applyMode);

  // The slider hides the least confident points first: at s (0-1000) the (s / 10) % least
  // confident are hidden; the label gives the confidence that leaves.
  const conf = points ? points.conf : new Float32Array(0);
  const n = conf.length;
  function applyThreshold() {
    const kept = Math.round(n * (1 - Number(slider.value) / 1000));
    if (points) points.object.geometry.setDrawRange(0, kept);
    const t = kept > 0 ? conf[kept - 1] : n ? conf[0] : 0;
    confLabel.textContent = `confidence >= ${Number(t.toPrecision(4))}: ${kept.toLocaleString()} of ${n.toLocaleString()} points`;
    requestRender();
  }
  // Start at the fusion's threshold: the points under it hidden.
  let under = 0;
  while (under < n && conf[n - 1 - under] < (data.min_conf || 0)) under++;
  slider.value = String(n ? Math.round((1000 * under) / n) : 0);
  slider.addEventListener('input', () => {
    // The threshold acts on the points: show them when only the mesh was shown.
    if (mode.value === 'mesh' && points) {
      mode.value = 'both';
      applyMode();
    }
    applyThreshold();
  });
  applyThreshold();
  applyMode();
  const showCams = document.getElementById('cameras');
  showCams.addEventListener('change', () => {
    frustums.visible = showCams.checked;
    requestRender();
  });

  buildGallery(data, lookFrom);
  buildSummary(data);
  buildMatches(data);
  status.textContent = '';
  render();

  // For tests and scripts: read back what the canvas shows.
  window.dens3rViewer = {
    ready: true,
    pixels() {
      render();
      const gl = renderer.getContext();
      const w = gl.drawingBufferWidth;
      const h = gl.drawingBufferHeight;
      const buf = new Uint8Array(w * h * 4);
      gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, buf);
      let s = '';
      for (let i = 0; i < buf.length; i += 0x8000) s += String.fromCharCode.apply(null, buf.subarray(i, i + 0x8000));
      return { width: w, height: h, rgba: btoa(s) };
    },
    lookFrom,
    startSlider: Number(slider.value),
  };
}

function buildGallery(data, lookFrom) {
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

function buildSummary(data) {
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

function buildMatches(data) {
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

window.addEventListener('DOMContentLoaded', main);
