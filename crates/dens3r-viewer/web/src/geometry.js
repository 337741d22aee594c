// The page's geometry: the point cloud, the mesh and the cameras' frustums as three.js
// objects, from the base64 arrays of viewer/scene.js (dens3r's world frame, OpenCV cameras,
// camera-to-world poses as row-major 4x4).

import {
  BufferAttribute,
  BufferGeometry,
  DoubleSide,
  Group,
  LineBasicMaterial,
  LineSegments,
  Matrix4,
  Mesh,
  MeshBasicMaterial,
  MeshNormalMaterial,
  PlaneGeometry,
  Points,
  PointsMaterial,
  SRGBColorSpace,
  Texture,
  Vector3,
} from 'three';

/** Decodes base64 into a typed array of the given constructor. */
export function decode(b64, Type) {
  const bin = atob(b64);
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return new Type(bytes.buffer);
}

/** The point cloud, sorted by confidence (highest first), so a threshold is a draw range. */
export function buildPoints(p) {
  const geo = new BufferGeometry();
  geo.setAttribute('position', new BufferAttribute(decode(p.positions, Float32Array), 3));
  geo.setAttribute('color', new BufferAttribute(decode(p.colors, Uint8Array), 3, true));
  const conf = decode(p.conf, Float32Array);
  const mat = new PointsMaterial({ size: p.point_size, vertexColors: true, sizeAttenuation: true });
  return { object: new Points(geo, mat), conf };
}

export function buildMesh(m) {
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

/** A camera's frustum (apex to the image corners at `depth`) and its photo on the far plane;
 * `onLoad` runs when the photo is ready to draw. */
export function buildFrustum(v, depth, onLoad) {
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
      onLoad();
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
