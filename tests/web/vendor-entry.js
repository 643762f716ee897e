// The parts of three.js the viewer uses (service/static/app.js), bundled and minified into
// service/static/vendor/three.min.js by `npm run build-vendor` (esbuild; three's version is pinned in package.json).
export {
  AxesHelper,
  BufferGeometry,
  Color,
  Float32BufferAttribute,
  Matrix4,
  PerspectiveCamera,
  Points,
  PointsMaterial,
  Scene,
  Sphere,
  Vector3,
  WebGLRenderer,
} from "three";
export { OrbitControls } from "three/addons/controls/OrbitControls.js";
