// A MuJoCo model's scene in three.js, posed by forward kinematics as MuJoCo poses it.
//
// Shared by the record view (record.js: a trial's scene at any tick, from its summary)
// and the live PR2 page (live/pr2.js: the robot now, from /joint_states and /tf). Both
// get the scene from the lab as labd/recorder/scene.py describes a model: bodies
// (parent, pose at rest, joints) and visible geoms (shape, size, colour, textures).
// three.js is passed in, so a page loads it when it needs it.

/**
 * The scene of ``info`` (``describe``'s bodies, geoms and textures): a three.js Scene
 * with lights, a Group per body holding its geoms, and ``pose(q)`` placing every body
 * for the joint positions ``q`` (MuJoCo's qpos).
 */
export async function buildScene(THREE, info) {
  const world = new THREE.Scene();
  world.background = new THREE.Color(0xdfe6ee);
  world.add(new THREE.HemisphereLight(0xffffff, 0x8a8a8a, 2.2));
  const sun = new THREE.DirectionalLight(0xffffff, 1.6);
  sun.position.set(2, 3, 6);
  world.add(sun);
  const loader = new THREE.TextureLoader();
  const textures = await Promise.all(info.textures.map(async (url) => {
    const texture = await loader.loadAsync(url);
    texture.colorSpace = THREE.SRGBColorSpace;
    texture.magFilter = THREE.NearestFilter;
    texture.wrapS = texture.wrapT = THREE.RepeatWrapping;
    return texture;
  }));
  const groups = info.bodies.map((body) => {
    const group = new THREE.Group();
    group.name = body.name;
    world.add(group);
    return group;
  });
  const solids = [];
  for (const geom of info.geoms) {
    const mesh = shape(THREE, geom, textures);
    if (!mesh) continue;
    mesh.position.fromArray(geom.pos);
    mesh.quaternion.fromArray(geom.quat);
    (geom.body < 0 ? world : groups[geom.body]).add(mesh);
    if (geom.shape !== "plane") solids.push(mesh);
  }
  const fk = kinematics(THREE, info.bodies);
  const pose = (q) => {
    fk.forward(q);
    groups.forEach((group, i) => {
      group.position.copy(fk.pos[i]);
      group.quaternion.copy(fk.quat[i]);
    });
  };
  return { world, groups, solids, pose, pos: fk.pos, quat: fk.quat };
}

/**
 * Forward kinematics as MuJoCo does it (mj_kinematics: free, ball, slide and hinge
 * joints): ``forward(q)`` fills ``pos`` and ``quat``, each body's pose in the world.
 */
export function kinematics(THREE, bodies) {
  const pos = bodies.map(() => new THREE.Vector3());
  const quat = bodies.map(() => new THREE.Quaternion());
  const v = new THREE.Vector3(), r = new THREE.Quaternion(), axis = new THREE.Vector3();
  const forward = (q) => {
    bodies.forEach((body, i) => {
      const p = pos[i].fromArray(body.pos), o = quat[i].fromArray(body.quat);
      if (body.parent >= 0) {
        p.applyQuaternion(quat[body.parent]).add(pos[body.parent]);
        o.premultiply(quat[body.parent]);
      }
      for (const [type, adr, ax, ay, az, jx, jy, jz, ref] of body.joints) {
        if (type === 0) {  // free: the body's pose in the world
          p.set(q[adr], q[adr + 1], q[adr + 2]);
          o.set(q[adr + 4], q[adr + 5], q[adr + 6], q[adr + 3]).normalize();
          continue;
        }
        const anchor = v.set(jx, jy, jz).applyQuaternion(o).add(p).clone();
        if (type === 2) {  // slide
          p.add(axis.set(ax, ay, az).applyQuaternion(o).multiplyScalar(q[adr] - ref));
          continue;
        }
        if (type === 3) r.setFromAxisAngle(axis.set(ax, ay, az), q[adr] - ref);
        else r.set(q[adr + 1], q[adr + 2], q[adr + 3], q[adr]).normalize();  // ball
        o.multiply(r);
        p.copy(anchor).sub(v.set(jx, jy, jz).applyQuaternion(o));
      }
    });
  };
  return { pos, quat, forward };
}

/** A camera looking at ``solids`` from ``view`` (a direction, in scene sizes), z up. */
export function frame(THREE, solids, view, aspect) {
  const bounds = new THREE.Box3();
  for (const mesh of solids) bounds.expandByObject(mesh);
  const camera = new THREE.PerspectiveCamera(45, aspect, 0.02, 200);
  camera.up.set(0, 0, 1);
  const centre = bounds.getCenter(new THREE.Vector3());
  const size = bounds.getSize(new THREE.Vector3()).length();
  camera.position.copy(centre).add(new THREE.Vector3(...view).multiplyScalar(size));
  return { camera, centre };
}

function shape(THREE, geom, textures) {
  const [a, b, c] = geom.size;
  let geometry, upright = false;
  switch (geom.shape) {
    case "box": geometry = new THREE.BoxGeometry(2 * a, 2 * b, 2 * c); break;
    case "sphere": geometry = new THREE.SphereGeometry(a, 20, 12); break;
    case "ellipsoid": geometry = new THREE.SphereGeometry(1, 20, 12).scale(a, b, c); break;
    case "cylinder": geometry = new THREE.CylinderGeometry(a, a, 2 * b, 24); upright = true; break;
    case "capsule": geometry = new THREE.CapsuleGeometry(a, 2 * b, 6, 16); upright = true; break;
    case "plane": geometry = new THREE.PlaneGeometry(2 * a, 2 * b); break;
    default: return null;
  }
  if (upright) geometry.rotateX(Math.PI / 2);  // MuJoCo's axis is z, three's is y
  const [red, green, blue, alpha] = geom.rgba;
  const material = new THREE.MeshLambertMaterial({
    color: new THREE.Color().setRGB(red, green, blue, THREE.SRGBColorSpace),
    transparent: alpha < 1, opacity: alpha });
  if (geom.texture !== undefined) {
    const texture = textures[geom.texture].clone();
    texture.repeat.set(geom.repeat[0], geom.repeat[1]);
    texture.needsUpdate = true;
    material.map = texture;
  }
  return new THREE.Mesh(geometry, material);
}
