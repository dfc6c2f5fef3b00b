// The offline asset viewer: three.js + Spark, bundled into one classic script so a page opened
// from disk (file://) runs it with no network and no module loading.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";

// Spark reads .ply, .splat and .spz as stored, all in the PLY (y-down) convention: a 180-degree
// turn about z puts them in the glTF frame of mesh.glb and splat.glb, as splat-transform maps them
// (docs/formats.md).
const PLY_TO_GLTF = new THREE.Quaternion(0, 0, 1, 0);

export function decodeBase64(text) {
  const raw = atob(text);
  const bytes = new Uint8Array(raw.length);
  for (let i = 0; i < raw.length; i++) bytes[i] = raw.charCodeAt(i);
  return bytes;
}

function parseGlb(bytes) {
  const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
  return new Promise((resolve, reject) => new GLTFLoader().parse(buffer, "", resolve, reject));
}

function nextFrames(count) {
  return new Promise((resolve) => {
    const step = () => (count-- <= 0 ? resolve() : requestAnimationFrame(step));
    requestAnimationFrame(step);
  });
}

// Spark sorts splats in a worker and draws what the last finished sort holds: nothing at first, and
// a splat already taken out of the scene until the next sort lands. On a loaded machine a sort takes
// longer than any fixed frame count, so wait for one to finish, then for `count` frames. Past
// `timeoutMs` it stops waiting and draws what it has, so a page never hangs on a sort.
function sortedFrames(spark, splatShown, count, timeoutMs = 60000) {
  const deadline = performance.now() + timeoutMs;
  const sorted = () => !spark || (!spark.sorting && !spark.sortDirty && (spark.activeSplats > 0 || !splatShown()));
  return new Promise((resolve) => {
    const step = () => (sorted() || performance.now() > deadline ? resolve() : requestAnimationFrame(step));
    requestAnimationFrame(step);
  }).then(() => nextFrames(count));
}

// Render an asset into `container`. opts: splat {bytes, type} or null; glb (mesh.glb, or a
// splat.glb shown as the POINTS a viewer without KHR_gaussian_splatting draws) or null;
// camera {position, target, fovY} in the glTF frame; width, height; interactive (orbit controls).
// Resolves once the scene is loaded and has been drawn a few times; returns toggles for the page.
export async function render(container, opts) {
  const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(opts.width, opts.height);
  renderer.setClearColor(opts.background ?? "#000000");
  container.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  const cam = opts.camera;
  const camera = new THREE.PerspectiveCamera(cam.fovY, opts.width / opts.height, cam.near ?? 0.005, cam.far ?? 50);
  camera.position.fromArray(cam.position);
  camera.up.set(0, 1, 0);
  camera.lookAt(new THREE.Vector3().fromArray(cam.target));
  scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 2.0));
  const parts = {};
  let spark = null;
  if (opts.splat) {
    spark = Object.assign(new SparkRenderer({ renderer }), opts.spark); // opts.spark: SparkRenderer fields
    scene.add(spark);
    const splat = new SplatMesh({ fileBytes: opts.splat.bytes, fileType: opts.splat.type });
    splat.quaternion.copy(PLY_TO_GLTF);
    scene.add(splat);
    await splat.initialized;
    parts.splat = splat;
  }
  if (opts.glb) {
    const gltf = await parseGlb(opts.glb);
    gltf.scene.traverse((node) => {
      if (node.isPoints) node.material.size = opts.pointSize ?? 2;
      // exporters often leave a mesh fully metallic, which draws black without an environment map
      if (node.isMesh) Object.assign(node.material, { metalness: 0, roughness: 0.9 });
    });
    scene.add(gltf.scene);
    parts.mesh = gltf.scene;
  }
  let controls = null;
  if (opts.interactive) {
    controls = new OrbitControls(camera, renderer.domElement);
    controls.target.fromArray(cam.target);
    controls.update();
  }
  renderer.setAnimationLoop(() => {
    if (controls) controls.update();
    renderer.render(scene, camera);
  });
  const splatShown = () => scene.children.includes(parts.splat);
  await sortedFrames(spark, splatShown, opts.settleFrames ?? 3);
  if (!opts.interactive) renderer.setAnimationLoop(null); // a still: stop drawing once settled
  return {
    show(name, visible) {
      // Spark keeps drawing a hidden SplatMesh, so a part is taken out of the scene instead
      if (parts[name] && visible) scene.add(parts[name]);
      if (parts[name] && !visible) scene.remove(parts[name]);
    },
    canvas: renderer.domElement,
    settle: (count) => sortedFrames(spark, splatShown, count), // resolves once drawn as it now stands
    dispose() {
      renderer.setAnimationLoop(null);
      renderer.dispose();
      renderer.forceContextLoss();
      renderer.domElement.remove();
    },
  };
}
