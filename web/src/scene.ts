// The 3D view: three.js with one WebGL2 renderer, the streamed tiles as meshes, orbit and fly
// navigation, and picking a point on the surface. Frames are drawn on demand (the camera moved,
// a tile came or went), not in a loop: software rendering (no GPU) stays cheap when nothing
// changes.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import type { VolumeInfo } from "./api";
import type { TileKey } from "./lod";
import { stitch, type TileMesh, type TriangleSet } from "./mesh";
import type { TileSink } from "./streamer";
import { colorAt, type Colormap } from "./colormap";
import type { Axis } from "./slice";
import type { Preview } from "./edit";
import { materialTextures, TEXTURE_LAYERS, TEXTURE_SIZE } from "./textures";

// Materials (`useMaterials`): a vertex carries the values at the two ends of the lattice edge it
// lies on and the weight of the second (`mesh.ts`, the material section). Values 0..7 become
// weights of eight slots (two vec4) that the triangle interpolates, so where materials meet the
// surface blends from one to the other instead of stepping; larger values keep their weight in
// one more slot, drawn in the value's palette colour. Value 0 (none) is drawn as the terrain is.
const VERTEX = /* glsl */ `
attribute vec4 material;
varying vec3 vNormal;
varying vec3 vPosition;
varying float vHeight;
varying vec4 vLow;
varying vec4 vHigh;
varying float vOther;
flat varying float vOtherValue;
uniform float heightScale;
vec4 slots(float value, float first) {
  return vec4(equal(vec4(value), vec4(first, first + 1.0, first + 2.0, first + 3.0)));
}
void main() {
  vec3 p = position;
  vNormal = normal;
  vPosition = p;
  vHeight = p.y * heightScale;
  float a = material.x;
  float b = material.y;
  float t = material.z / 255.0;
  vLow = slots(a, 0.0) * (1.0 - t) + slots(b, 0.0) * t;
  vHigh = slots(a, 4.0) * (1.0 - t) + slots(b, 4.0) * t;
  vOther = (a >= 8.0 ? 1.0 - t : 0.0) + (b >= 8.0 ? t : 0.0);
  vOtherValue = a >= 8.0 ? a : b;
  gl_Position = projectionMatrix * modelViewMatrix * vec4(p, 1.0);
}`;

const FRAGMENT = /* glsl */ `
varying vec3 vNormal;
varying vec3 vPosition;
varying float vHeight;
varying vec4 vLow;
varying vec4 vHigh;
varying float vOther;
flat varying float vOtherValue;
uniform vec3 sun;
// 0: the terrain's grass and rock; otherwise the number of colour map stops (height through it).
uniform int stopCount;
uniform vec3 stops[10];
// 1: colour by material (the palette's colours, textured), the rest as the terrain.
uniform int useMaterials;
uniform sampler2D palette;
uniform sampler2DArray detail;
uniform float textureScale;
vec3 colormap(float t) {
  float x = clamp(t, 0.0, 1.0) * float(stopCount - 1);
  int i = int(min(floor(x), float(stopCount - 2)));
  vec3 a = stops[0];
  vec3 b = stops[1];
  for (int k = 0; k < 9; k++) {
    if (k == i) { a = stops[k]; b = stops[k + 1]; }
  }
  return mix(a, b, x - float(i));
}
vec3 paletteColor(float value) {
  return texelFetch(palette, ivec2(int(value), 0), 0).rgb;
}
// Triplanar mapping: the texture projected along each axis, weighted by how much the surface
// faces that axis.
float textured(float layer, vec3 blend) {
  vec3 p = vPosition * textureScale;
  return (texture(detail, vec3(p.yz, layer)).r * blend.x
    + texture(detail, vec3(p.xz, layer)).r * blend.y
    + texture(detail, vec3(p.xy, layer)).r * blend.z) * (255.0 / 200.0);
}
void main() {
  vec3 n = normalize(vNormal);
  float light = 0.38 + 0.62 * max(dot(n, sun), 0.0);
  vec3 rock = mix(vec3(0.45, 0.36, 0.28), vec3(0.62, 0.60, 0.58), clamp(vHeight, 0.0, 1.0));
  vec3 grass = mix(vec3(0.30, 0.52, 0.20), vec3(0.55, 0.62, 0.30), clamp(vHeight, 0.0, 1.0));
  vec3 terrain = mix(rock, grass, smoothstep(0.55, 0.8, n.y));
  vec3 base;
  if (useMaterials == 1) {
    vec3 blend = pow(abs(n), vec3(4.0));
    blend /= blend.x + blend.y + blend.z;
    float weights[8] = float[8](vLow.x, vLow.y, vLow.z, vLow.w, vHigh.x, vHigh.y, vHigh.z, vHigh.w);
    float total = vOther;
    base = vOther * paletteColor(vOtherValue);
    for (int i = 0; i < 8; i++) {
      float w = weights[i];
      if (w < 0.004) continue;
      total += w;
      base += w * (i == 0 ? terrain : paletteColor(float(i)) * textured(float(i), blend));
    }
    base = total > 0.0 ? base / total : terrain;
  } else if (stopCount == 0) {
    base = terrain;
  } else {
    base = colormap(vHeight);
  }
  gl_FragColor = vec4(base * light, 1.0);
}`;

/** The sky behind the volume (also what the browser tests tell from the surface). */
export const SKY = 0x9cc4e4;

/**
 * A frame drawn while tiles stream in is followed by a pause of this many times its cost
 * (`requestRender`). With software rendering the close view's frames cost 250-500 ms each; at
 * 4 the close view completed 15-25% sooner than at 2 (docs/benchmarks.md, "The web viewer").
 */
const FRAME_PAUSE = 4;

interface TileView {
  mesh: THREE.Mesh;
  data: TileMesh;
  /** The faces whose strips are drawn (and whose moves are applied). */
  mask: number;
}

export type Navigation = "orbit" | "fly";

export class Viewport implements TileSink {
  readonly renderer: THREE.WebGLRenderer;
  readonly camera: THREE.PerspectiveCamera;
  private readonly scene = new THREE.Scene();
  private readonly tiles = new Map<string, TileView>();
  private plane: THREE.Group | null = null;
  /** The page's own edits drawn until the server's tiles show them, by id. */
  private readonly previews = new Map<number, THREE.Mesh>();
  private previewId = 0;
  /** Segment meshes shown from the segment list, by key (decimal id, exact for u64 ids). */
  private readonly segments = new Map<string, THREE.Mesh>();
  private readonly material: THREE.ShaderMaterial;
  private readonly orbit: OrbitControls;
  private readonly fly: FlyNavigation;
  private frameRequested = false;
  /** The timer of a frame put off until `nextFrameAt`, if one is. */
  private frameTimer: ReturnType<typeof setTimeout> | null = null;
  /** A frame was asked for and when to draw it is decided at the end of the task. */
  private deciding = false;
  /** The frame being decided is drawn at once, pause or not (`requestRender(true)`). */
  private frameNow = false;
  /** When the next frame may be drawn (performance.now()), after the last one's pause. */
  private nextFrameAt = 0;
  /**
   * Whether responses are on their way (the streamer's requests in flight): only then does a
   * frame wait for the last one's pause, which keeps the main thread free for them.
   */
  busy: () => boolean = () => true;
  private readonly frustum = new THREE.Frustum();
  private readonly projScreen = new THREE.Matrix4();
  navigation: Navigation = "orbit";
  /** Called after each frame with the number of tiles drawn. */
  onFrame: (tiles: number) => void = () => {};
  /** Called when the person moved the camera. */
  onCameraChange: () => void = () => {};

  constructor(canvas: HTMLCanvasElement) {
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: false, powerPreference: "high-performance" });
    this.renderer.setPixelRatio(1);
    this.renderer.setClearColor(SKY);
    this.camera = new THREE.PerspectiveCamera(60, 1, 1, 10_000);
    const uniforms = {
      sun: { value: new THREE.Vector3(0.4, 0.8, 0.45).normalize() },
      heightScale: { value: 1 / 256 },
      stopCount: { value: 0 },
      stops: { value: Array.from({ length: 10 }, () => new THREE.Vector3()) },
      useMaterials: { value: 0 },
      palette: { value: paletteTexture([]) },
      detail: { value: detailTexture() },
      textureScale: { value: 1 / 16 },
    };
    this.material = new THREE.ShaderMaterial({ vertexShader: VERTEX, fragmentShader: FRAGMENT, uniforms });
    // Light for the segment meshes (the surface's own shader lights itself).
    const sunLight = new THREE.DirectionalLight(0xffffff, 2.2);
    sunLight.position.set(0.4, 0.8, 0.45);
    this.scene.add(new THREE.AmbientLight(0xffffff, 0.9), sunLight);
    this.orbit = new OrbitControls(this.camera, canvas);
    this.orbit.addEventListener("change", () => {
      this.requestRender();
      this.onCameraChange();
    });
    this.fly = new FlyNavigation(this.camera, canvas, () => {
      this.requestRender();
      this.onCameraChange();
    });
    this.fly.enabled = false;
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
  }

  /** Whether the canvas got a WebGL2 context (three.js requires one). */
  get webgl2(): boolean {
    return this.renderer.getContext() instanceof WebGL2RenderingContext;
  }

  get target(): THREE.Vector3 {
    return this.orbit.target;
  }

  setNavigation(n: Navigation): void {
    this.navigation = n;
    this.orbit.enabled = n === "orbit";
    this.fly.enabled = n === "fly";
    if (n === "orbit") {
      // Orbit around the point the fly camera was looking at, as far away as before.
      const d = this.camera.position.distanceTo(this.orbit.target);
      const dir = new THREE.Vector3();
      this.camera.getWorldDirection(dir);
      this.orbit.target.copy(this.camera.position).addScaledVector(dir, d);
      this.orbit.update();
    }
  }

  /** Frames the volume: its scale for colours and clipping, and, unless given, a default view. */
  setVolume(info: VolumeInfo, view?: { position: THREE.Vector3; target: THREE.Vector3 }): void {
    const size = new THREE.Vector3(...info.dims).multiply(new THREE.Vector3(...info.voxel_scale));
    const extent = Math.max(size.x, size.y, size.z);
    this.material.uniforms["heightScale"]!.value = 1 / Math.max(size.y, 1);
    // The textures repeat every 16 voxels (4 texels a voxel).
    this.material.uniforms["textureScale"]!.value = 1 / (16 * Math.min(...info.voxel_scale));
    this.camera.near = extent / 2000;
    this.camera.far = extent * 20;
    this.camera.updateProjectionMatrix();
    this.fly.speed = extent / 4;
    // By default: the whole volume in view, seen from above one corner.
    const target = view?.target ?? size.clone().multiplyScalar(0.5);
    const radius = size.length() / 2;
    const fovY = THREE.MathUtils.degToRad(this.camera.fov);
    const fovX = 2 * Math.atan(Math.tan(fovY / 2) * this.camera.aspect);
    const distance = (0.72 * radius) / Math.sin(Math.min(fovX, fovY) / 2);
    const position =
      view?.position ??
      target.clone().add(new THREE.Vector3(-0.45, 0.6, 0.85).normalize().multiplyScalar(distance));
    this.camera.position.copy(position);
    this.orbit.target.copy(target);
    this.camera.lookAt(target);
    this.orbit.update();
    this.requestRender();
  }

  /**
   * Colours the surface by height through `map` ("terrain": grass and rock; "materials": by the
   * material its vertices carry, `setPalette`'s colours, textured).
   */
  setColormap(map: Colormap): void {
    const u = this.material.uniforms;
    u["useMaterials"]!.value = map === "materials" ? 1 : 0;
    if (map === "terrain" || map === "materials") {
      u["stopCount"]!.value = 0;
    } else {
      const stops = u["stops"]!.value as THREE.Vector3[];
      for (let i = 0; i < 10; i++) {
        const [r, g, b] = colorAt(map, i / 9);
        // A ShaderMaterial's gl_FragColor goes out as it is: the map's sRGB values as they are.
        stops[i]!.set(r / 255, g / 255, b / 255);
      }
      u["stopCount"]!.value = 10;
    }
    this.requestRender();
  }

  /** The colours of material values (index = value; "#rrggbb"), for the "materials" map. */
  setPalette(colors: readonly string[]): void {
    const u = this.material.uniforms["palette"]!;
    (u.value as THREE.Texture).dispose();
    u.value = paletteTexture(colors);
    this.requestRender();
  }

  /**
   * Draws the slice's plane in the view (a translucent square across the volume with its
   * outline), or removes it.
   */
  setSlicePlane(plane: { axis: Axis; position: number; size: THREE.Vector3 } | null): void {
    if (this.plane) {
      this.scene.remove(this.plane);
      this.plane.traverse((o) => {
        if (o instanceof THREE.Mesh || o instanceof THREE.LineSegments) o.geometry.dispose();
      });
      this.plane = null;
    }
    if (plane) {
      const { axis, position, size } = plane;
      const a = axis === "x" ? 0 : axis === "y" ? 1 : 2;
      const box = new THREE.BoxGeometry(
        a === 0 ? 0 : size.x,
        a === 1 ? 0 : size.y,
        a === 2 ? 0 : size.z,
      );
      const group = new THREE.Group();
      const fill = new THREE.Mesh(
        box,
        new THREE.MeshBasicMaterial({ color: 0xffd040, transparent: true, opacity: 0.18, side: THREE.DoubleSide, depthWrite: false }),
      );
      const edges = new THREE.LineSegments(new THREE.EdgesGeometry(box), new THREE.LineBasicMaterial({ color: 0xffb000 }));
      group.add(fill, edges);
      const center = size.clone().multiplyScalar(0.5);
      center.setComponent(a, position);
      group.position.copy(center);
      this.plane = group;
      this.scene.add(group);
    }
    this.requestRender();
  }

  // --- segments (the segment list's sink) -------------------------------------------------

  /**
   * Shows segment `id`'s closed mesh in `color` (lit, drawn over the surface where both lie:
   * a segment's boundary on the surface is the surface).
   */
  showSegment(id: string, mesh: TriangleSet, color: [number, number, number]): void {
    this.hideSegment(id);
    const material = new THREE.MeshLambertMaterial({
      color: new THREE.Color().setRGB(color[0] / 255, color[1] / 255, color[2] / 255, THREE.SRGBColorSpace),
      polygonOffset: true,
      polygonOffsetFactor: -1,
      polygonOffsetUnits: -4,
    });
    const m = new THREE.Mesh(geometry(mesh), material);
    m.matrixAutoUpdate = false;
    this.scene.add(m);
    this.segments.set(id, m);
    this.requestRender();
  }

  hideSegment(id: string): void {
    const m = this.segments.get(id);
    if (!m) return;
    this.scene.remove(m);
    m.geometry.dispose();
    (m.material as THREE.Material).dispose();
    this.segments.delete(id);
    this.requestRender();
  }

  /** Segment meshes shown. */
  get segmentCount(): number {
    return this.segments.size;
  }

  // --- tiles (the streamer's sink) ----------------------------------------------------------

  show(
    id: string,
    _key: TileKey,
    data: TileMesh,
    mask = 0,
    strips: ReadonlyArray<TileMesh | null> = [],
  ): void {
    this.hide(id);
    const mesh = new THREE.Mesh(geometry(stitch(data, mask, strips), mask === 0 ? data : undefined), this.material);
    mesh.matrixAutoUpdate = false;
    this.scene.add(mesh);
    this.tiles.set(id, { mesh, data, mask });
    if (this.seen(mesh)) this.requestRender();
  }

  hide(id: string): void {
    const t = this.tiles.get(id);
    if (!t) return;
    this.scene.remove(t.mesh);
    t.mesh.geometry.dispose();
    this.tiles.delete(id);
    if (this.seen(t.mesh)) this.requestRender();
  }

  /** Whether a tile's mesh is in the view frustum (a tile outside it changes no frame). */
  private seen(mesh: THREE.Mesh): boolean {
    const g = mesh.geometry;
    if (!g.boundingSphere) g.computeBoundingSphere();
    this.camera.updateMatrixWorld();
    this.frustum.setFromProjectionMatrix(
      this.projScreen.multiplyMatrices(this.camera.projectionMatrix, this.camera.matrixWorldInverse),
    );
    return g.boundingSphere ? this.frustum.intersectsSphere(g.boundingSphere) : true;
  }

  get tileCount(): number {
    return this.tiles.size;
  }

  /**
   * Whether a frame was asked for and not drawn yet: what the view shows may then be older than
   * its tiles (a frame after a recent one waits out that one's pause, `requestRender`).
   */
  get framePending(): boolean {
    return this.frameRequested;
  }

  // --- frames, picking --------------------------------------------------------------------

  /**
   * Draws a frame soon. A frame that takes long (software rendering: about 100 ms for the
   * default view, several hundred close to the ground, during which the page's main thread
   * waits for the canvas to be read back) is followed by a pause of `FRAME_PAUSE` times its
   * length while requests are in flight (`busy`), so that drawing takes at most a fifth of the
   * main thread while tiles stream in and their responses are not kept waiting. With nothing in
   * flight (the last tile of an edit arrived and its region swapped, or a quiet moment), or
   * when `now` (the frame that completes the view) the frame is drawn at once.
   */
  requestRender(now = false): void {
    if (now) this.frameNow = true;
    // Drawn at the next animation frame already, or decided below.
    if ((this.frameRequested && this.frameTimer === null) || this.deciding) return;
    this.deciding = true;
    // Decided once the caller's task is done: a streamer's plan shows tiles before it starts
    // its next requests.
    queueMicrotask(() => {
      this.deciding = false;
      const wait = this.busy() && !this.frameNow ? this.nextFrameAt - performance.now() : 0;
      this.frameNow = false;
      if (this.frameRequested) {
        // A frame put off for the pause is drawn now when no response waits any more.
        if (this.frameTimer === null || wait > 1) return;
        clearTimeout(this.frameTimer);
      }
      this.frameRequested = true;
      if (wait > 1) this.frameTimer = setTimeout(() => this.frame(), wait);
      else this.frame();
    });
  }

  private frame(): void {
    this.frameTimer = null;
    requestAnimationFrame(() => {
      this.frameRequested = false;
      if (this.fly.enabled && this.fly.step()) this.requestRender();
      const start = performance.now();
      this.renderer.render(this.scene, this.camera);
      this.onFrame(this.tiles.size);
      // The frame's cost includes the browser's work after this callback (compositing, and
      // with SwiftShader the rasterizing): it ends when the next task runs.
      setTimeout(() => {
        const end = performance.now();
        this.nextFrameAt = end + FRAME_PAUSE * (end - start);
      }, 0);
    });
  }

  private resize(): void {
    const c = this.renderer.domElement;
    const w = Math.max(1, c.clientWidth);
    const h = Math.max(1, c.clientHeight);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.requestRender();
  }

  /**
   * Draws the page's own edit at once (`edit.ts` `previewOf`), in the volume's world units
   * (`scale`: the voxel scale), until `removePreview` with the id this returns.
   */
  addPreview(p: Preview, scale: readonly number[]): number {
    const g = previewGeometry(p);
    const material =
      p.effect === "add"
        ? this.material
        : new THREE.MeshBasicMaterial({
            color: p.effect === "carve" ? 0xd03020 : 0x808080,
            transparent: true,
            opacity: 0.45,
            depthWrite: false,
          });
    const mesh = new THREE.Mesh(g, material);
    mesh.position.set(...(p.center.map((c, a) => c * (scale[a] ?? 1)) as [number, number, number]));
    mesh.scale.set(...([0, 1, 2].map((a) => scale[a] ?? 1) as [number, number, number]));
    this.scene.add(mesh);
    const id = ++this.previewId;
    this.previews.set(id, mesh);
    this.requestRender();
    return id;
  }

  removePreview(id: number): void {
    const mesh = this.previews.get(id);
    if (!mesh) return;
    this.previews.delete(id);
    this.scene.remove(mesh);
    mesh.geometry.dispose();
    if (mesh.material !== this.material) (mesh.material as THREE.Material).dispose();
    this.requestRender();
  }

  /** Edits drawn as previews now. */
  get previewCount(): number {
    return this.previews.size;
  }

  /** The ray from the camera through canvas pixel (x, y) (CSS pixels). */
  ray(x: number, y: number): THREE.Raycaster {
    const c = this.renderer.domElement;
    const ndc = new THREE.Vector2((x / c.clientWidth) * 2 - 1, -(y / c.clientHeight) * 2 + 1);
    const ray = new THREE.Raycaster();
    ray.setFromCamera(ndc, this.camera);
    return ray;
  }

  /** The point of the surface under canvas pixel (x, y), if any. */
  pick(x: number, y: number): THREE.Vector3 | null {
    const hits = this.ray(x, y).intersectObjects([...this.tiles.values()].map((t) => t.mesh), false);
    return hits[0]?.point ?? null;
  }

  /** Where a world point appears on the canvas, in CSS pixels. */
  project(p: THREE.Vector3): { x: number; y: number } {
    const c = this.renderer.domElement;
    const v = p.clone().project(this.camera);
    return { x: ((v.x + 1) / 2) * c.clientWidth, y: ((1 - v.y) / 2) * c.clientHeight };
  }
}

/** A preview's shape in voxel units, centred on the origin (`edit.ts` `previewOf`, icvg.md). */
function previewGeometry(p: Preview): THREE.BufferGeometry {
  const [hx, hy, hz] = p.half;
  switch (p.primitive) {
    case "ellipsoid":
      return new THREE.SphereGeometry(1, 24, 16).scale(hx, hy, hz);
    case "cuboid":
      return new THREE.BoxGeometry(2 * hx, 2 * hy, 2 * hz);
    case "cylinder":
      return new THREE.CylinderGeometry(1, 1, 2 * hy, 24).scale(hx, 1, hz);
    case "cone":
      // Apex up.
      return new THREE.ConeGeometry(1, 2 * hy, 24).scale(hx, 1, hz);
    case "pyramid":
      // Four sides (a cone of four segments, turned so they face the axes), apex up.
      return new THREE.ConeGeometry(Math.SQRT2, 2 * hy, 4).rotateY(Math.PI / 4).scale(hx, 1, hz);
    case "torus":
      // Around +y: three's torus lies in the x-y plane around z.
      return new THREE.TorusGeometry(hx - (p.minor ?? 1), p.minor ?? 1, 12, 32).rotateX(Math.PI / 2);
    case "capsule": {
      const r = p.minor ?? hx;
      return new THREE.CapsuleGeometry(r, Math.max(0, 2 * (hy - r)), 8, 16);
    }
    case "prism": {
      // The wedge below the plane through the top of its -x face and the bottom of its +x face:
      // a right triangle in x-y, from z -hz to +hz (its two ends and three sides, outwards).
      const [a, b, c] = [[-hx, -hy], [hx, -hy], [-hx, hy]] as const;
      const v = (p: readonly [number, number], z: number) => [p[0], p[1], z];
      const quad = (p: readonly [number, number], q: readonly [number, number]) => [
        ...v(p, -hz), ...v(q, -hz), ...v(q, hz),
        ...v(p, -hz), ...v(q, hz), ...v(p, hz),
      ];
      const positions = [
        ...v(a, hz), ...v(b, hz), ...v(c, hz),
        ...v(a, -hz), ...v(c, -hz), ...v(b, -hz),
        ...quad(a, b), ...quad(b, c), ...quad(c, a),
      ];
      const g = new THREE.BufferGeometry();
      g.setAttribute("position", new THREE.Float32BufferAttribute(positions, 3));
      g.computeVertexNormals();
      return g;
    }
  }
}

/** A tile's triangles as GPU buffers, with bounds from the header (no scan of the positions). */
/** A tile's triangles on the GPU; `bounds` (the decoder's, of the regular mesh drawn alone)
 * spares computing them; three.js computes those of a stitched tile (its strips can reach beyond
 * the regular mesh's bounds). */
function geometry(t: TriangleSet, bounds?: { min: number[]; max: number[] }): THREE.BufferGeometry {
  const g = new THREE.BufferGeometry();
  g.setAttribute("position", new THREE.BufferAttribute(t.positions, 3));
  g.setAttribute("normal", new THREE.BufferAttribute(t.normals, 3, true));
  g.setIndex(new THREE.BufferAttribute(t.indices, 1));
  // Bytes as they are: the shader reads the values 0..255, not normalized.
  if (t.materials) g.setAttribute("material", new THREE.BufferAttribute(t.materials, 4));
  if (bounds) {
    g.boundingBox = new THREE.Box3(new THREE.Vector3(...bounds.min), new THREE.Vector3(...bounds.max));
    g.boundingSphere = g.boundingBox.getBoundingSphere(new THREE.Sphere());
  }
  return g;
}

/** 256 colours in a row, value i at texel i (grey for values the palette does not give). */
function paletteTexture(colors: readonly string[]): THREE.DataTexture {
  const data = new Uint8Array(256 * 4);
  for (let i = 0; i < 256; i++) {
    const m = /^#?([0-9a-f]{6})$/i.exec(colors[i] ?? "");
    const hex = m ? parseInt(m[1]!, 16) : 0x808080;
    data.set([hex >> 16, (hex >> 8) & 255, hex & 255, 255], 4 * i);
  }
  const t = new THREE.DataTexture(data, 256, 1, THREE.RGBAFormat, THREE.UnsignedByteType);
  t.needsUpdate = true;
  return t;
}

/** The materials' surface patterns (`textures.ts`), repeating, mipmapped. */
function detailTexture(): THREE.DataArrayTexture {
  const t = new THREE.DataArrayTexture(materialTextures(), TEXTURE_SIZE, TEXTURE_SIZE, TEXTURE_LAYERS);
  t.format = THREE.RGBAFormat;
  t.type = THREE.UnsignedByteType;
  t.wrapS = THREE.RepeatWrapping;
  t.wrapT = THREE.RepeatWrapping;
  t.magFilter = THREE.LinearFilter;
  t.minFilter = THREE.LinearMipmapLinearFilter;
  t.generateMipmaps = true;
  t.needsUpdate = true;
  return t;
}

/** Fly navigation: drag to look, W/A/S/D (or arrows) to move, Q/E down and up, Shift faster. */
class FlyNavigation {
  enabled = true;
  speed = 100;
  private readonly keys = new Set<string>();
  private last = 0;
  private yaw = 0;
  private pitch = 0;

  constructor(
    private readonly camera: THREE.PerspectiveCamera,
    canvas: HTMLCanvasElement,
    private readonly changed: () => void,
  ) {
    let drag: { x: number; y: number } | null = null;
    canvas.addEventListener("pointerdown", (e) => {
      if (!this.enabled) return;
      drag = { x: e.clientX, y: e.clientY };
      this.syncAngles();
    });
    window.addEventListener("pointerup", () => (drag = null));
    window.addEventListener("pointermove", (e) => {
      if (!this.enabled || !drag) return;
      this.yaw -= (e.clientX - drag.x) * 0.004;
      this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch - (e.clientY - drag.y) * 0.004));
      drag = { x: e.clientX, y: e.clientY };
      this.camera.quaternion.setFromEuler(new THREE.Euler(this.pitch, this.yaw, 0, "YXZ"));
      this.changed();
    });
    window.addEventListener("keydown", (e) => {
      if (!this.enabled || (e.target as HTMLElement | null)?.closest?.("input, select, textarea")) return;
      this.keys.add(e.key.toLowerCase());
      this.last = performance.now();
      this.changed();
    });
    window.addEventListener("keyup", (e) => this.keys.delete(e.key.toLowerCase()));
    window.addEventListener("blur", () => this.keys.clear());
  }

  private syncAngles(): void {
    const e = new THREE.Euler().setFromQuaternion(this.camera.quaternion, "YXZ");
    this.yaw = e.y;
    this.pitch = e.x;
  }

  /** Moves the camera for the time since the last step; whether keys are still held. */
  step(): boolean {
    if (this.keys.size === 0) return false;
    const now = performance.now();
    const dt = Math.min(0.1, (now - this.last) / 1000);
    this.last = now;
    const k = (...names: string[]) => (names.some((n) => this.keys.has(n)) ? 1 : 0);
    const move = new THREE.Vector3(
      k("d", "arrowright") - k("a", "arrowleft"),
      k("e") - k("q"),
      k("s", "arrowdown") - k("w", "arrowup"),
    );
    if (move.lengthSq() === 0) return false;
    move.normalize().multiplyScalar(this.speed * dt * (this.keys.has("shift") ? 4 : 1));
    this.camera.position.add(move.applyQuaternion(this.camera.quaternion));
    this.changed();
    return true;
  }
}
