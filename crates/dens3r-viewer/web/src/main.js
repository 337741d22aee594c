// The page dens3r writes beside a reconstruction (OUT/index.html): the point cloud and mesh,
// the cameras as frustums with their photos, a confidence slider, per-view pictures, match
// pictures and the run's summary. Its data is `window.DENS3R_SCENE`, set by viewer/scene.js
// (written by the `dens3r-viewer` crate); everything loads from the file system, no server.
//
// Conventions: the data is in dens3r's world frame (OpenCV: x right, y down, z forward,
// camera-to-world poses, row-major 4x4); the page turns the whole scene half a turn about x
// so that the first camera's up is the page's up.

import { Color, Group, PerspectiveCamera, Scene, Vector3, WebGLRenderer } from 'three';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { buildFrustum, buildMesh, buildPoints } from './geometry.js';
import { buildGallery, buildMatches, buildSummary, el } from './panels.js';

const BACKGROUND = 0x1d2024;

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
    const f = buildFrustum(v, depth, () => requestRender());
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
  // Point size: the page's guess (the sampled pixels' spacing) times 2^value.
  const psize = document.getElementById('psize');
  psize.disabled = !points;
  psize.addEventListener('input', () => {
    if (points) points.object.material.size = data.points.point_size * 2 ** Number(psize.value);
    requestRender();
  });
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

window.addEventListener('DOMContentLoaded', main);
