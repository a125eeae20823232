// What three.js draws of a glTF file under the server's camera and lights: the reference the
// server's POST /v1/crowd/render is compared with (tests/server/threejs.rs).
//
// window.renderReference(config) loads config.model with GLTFLoader (the original .gltf, its
// buffers and images beside it), sets the morph weights, draws one frame and resolves to the
// canvas as a PNG data URL. Everything that decides the picture comes from the test:
//
//   width, height       the canvas, in device pixels (pixel ratio 1)
//   background          sRGB 0-255, as the render request's image.background
//   camera              {position, target, up, fovY (degrees), near, far}: the server's view
//   lights              {key, fill: {direction (unit, world, toward the light), intensity},
//                        up, sky, ground (linear RGB)}: crowdmorph's brdf::reference_lights
//   weights             {name: weight}; every influence not named is 0, as the server's
//                       named live weights. A target the file does not name is target_<i> on
//                       the server (the importer's name), and index i here.
//   flipV               optional: every texture read upside down (v -> 1 - v), the control the
//                       test draws to show that its comparison sees a flipped texture.
//   frame               optional: {positions, normals}, one flat x,y,z array per mesh in
//                       traversal order: the vertex buffers of a crowd frame, written into the
//                       loaded model's geometry before drawing (how a three.js client animates
//                       the server's model.glb, which has no morph targets).
//
// Why these settings: the server shades with glTF's metallic-roughness BRDF into an sRGB
// target with no tone mapping, under two directional lights and a hemisphere ambient with no
// environment map. three's MeshStandardMaterial with DirectionalLight (intensity = irradiance,
// r155+ physically based units) and HemisphereLight is the same model, so outputColorSpace
// sRGB and NoToneMapping are what make the two pictures comparable.

import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

const linear = (rgb) => new THREE.Color().setRGB(rgb[0], rgb[1], rgb[2], THREE.LinearSRGBColorSpace);

async function renderReference(config) {
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(config.width, config.height);
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  renderer.toneMapping = THREE.NoToneMapping;
  const bg = config.background.map((c) => c / 255);
  renderer.setClearColor(new THREE.Color().setRGB(bg[0], bg[1], bg[2], THREE.SRGBColorSpace), 1);
  document.body.replaceChildren(renderer.domElement);

  const gltf = await new GLTFLoader().loadAsync(config.model);
  const scene = new THREE.Scene();
  scene.add(gltf.scene);

  const applied = {};
  const meshes = [];
  gltf.scene.traverse((o) => {
    if (!o.isMesh) return;
    meshes.push(o.name);
    if (!o.morphTargetInfluences) return;
    o.morphTargetInfluences.fill(0);
    for (const [name, weight] of Object.entries(config.weights)) {
      let i = o.morphTargetDictionary?.[name];
      const unnamed = /^target_(\d+)$/.exec(name);
      if (i === undefined && unnamed) i = Number(unnamed[1]);
      if (i === undefined || i >= o.morphTargetInfluences.length) continue;
      o.morphTargetInfluences[i] = weight;
      applied[name] = (applied[name] ?? 0) + 1;
    }
  });
  if (config.frame) {
    const { positions, normals } = config.frame;
    let i = 0;
    gltf.scene.traverse((o) => {
      if (!o.isMesh) return;
      const g = o.geometry;
      if (i >= positions.length) throw new Error(`the frame has ${positions.length} meshes, the model more`);
      for (const [name, data] of [['position', positions[i]], ['normal', normals[i]]]) {
        const attr = g.getAttribute(name);
        if (!attr || attr.array.length !== data.length) {
          throw new Error(`mesh ${i}: ${name} has ${attr?.array.length} components, the frame ${data.length}`);
        }
        attr.array.set(data);
        attr.needsUpdate = true;
      }
      g.computeBoundingBox();
      g.computeBoundingSphere();
      i += 1;
    });
    if (i !== positions.length) throw new Error(`the frame has ${positions.length} meshes, the model ${i}`);
  }
  for (const name of Object.keys(config.weights)) {
    if (!applied[name]) throw new Error(`no mesh of ${config.model} has a target ${name}`);
  }

  const c = config.camera;
  const camera = new THREE.PerspectiveCamera(c.fovY, config.width / config.height, c.near, c.far);
  camera.up.fromArray(c.up);
  camera.position.fromArray(c.position);
  camera.lookAt(new THREE.Vector3().fromArray(c.target));
  camera.updateMatrixWorld();

  const l = config.lights;
  for (const d of [l.key, l.fill]) {
    const light = new THREE.DirectionalLight(0xffffff, d.intensity);
    // three lights along position − target; the target stays at the origin.
    light.position.fromArray(d.direction);
    scene.add(light);
  }
  const hemi = new THREE.HemisphereLight(linear(l.sky), linear(l.ground), 1);
  hemi.position.fromArray(l.up);
  scene.add(hemi);

  if (config.flipV) {
    gltf.scene.traverse((o) => {
      for (const m of o.isMesh ? [o.material].flat() : []) {
        for (const t of [m.map, m.aoMap, m.normalMap, m.roughnessMap, m.emissiveMap]) {
          if (!t) continue;
          t.repeat.set(1, -1);
          t.offset.set(0, 1);
        }
      }
    });
  }

  renderer.render(scene, camera);
  const gl = renderer.getContext();
  const info = {
    meshes,
    applied,
    samples: gl.getParameter(gl.SAMPLES),
    renderer: gl.getParameter(gl.RENDERER),
    revision: THREE.REVISION,
  };
  const png = renderer.domElement.toDataURL('image/png');
  // Each call draws with a context of its own; give it back rather than wait for the
  // collector (Chromium keeps only a few live WebGL contexts per page).
  renderer.dispose();
  renderer.forceContextLoss();
  return { png, info };
}

window.renderReference = renderReference;
document.title = 'ready';
