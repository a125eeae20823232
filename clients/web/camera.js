// Matrices (column-major, as WebGL wants them) and the orbit camera: drag to turn, shift-drag
// or right-drag to pan, wheel to zoom. World units are the rig's; +Y is up, heads face +Z.

export function perspective(fovYDeg, aspect, near, far) {
  const f = 1 / Math.tan((fovYDeg * Math.PI) / 360);
  const nf = 1 / (near - far);
  return new Float32Array([
    f / aspect, 0, 0, 0,
    0, f, 0, 0,
    0, 0, (far + near) * nf, -1,
    0, 0, 2 * far * near * nf, 0,
  ]);
}

function sub(a, b) {
  return [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
}

function cross(a, b) {
  return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
}

function normalize(a) {
  const l = Math.hypot(a[0], a[1], a[2]) || 1;
  return [a[0] / l, a[1] / l, a[2] / l];
}

function dot(a, b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

export function lookAt(eye, target, up) {
  const z = normalize(sub(eye, target));
  const x = normalize(cross(up, z));
  const y = cross(z, x);
  return new Float32Array([
    x[0], y[0], z[0], 0,
    x[1], y[1], z[1], 0,
    x[2], y[2], z[2], 0,
    -dot(x, eye), -dot(y, eye), -dot(z, eye), 1,
  ]);
}

export function multiply(a, b) {
  const out = new Float32Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      out[c * 4 + r] = s;
    }
  }
  return out;
}

/** translate(position) · rotate_y(yaw) · scale, as the server places heads. */
export function placement(position, yawDeg, scale) {
  const t = (yawDeg * Math.PI) / 180;
  const c = Math.cos(t) * scale;
  const s = Math.sin(t) * scale;
  return new Float32Array([
    c, 0, -s, 0,
    0, scale, 0, 0,
    s, 0, c, 0,
    position[0], position[1], position[2], 1,
  ]);
}

/** A camera turning about a target point. */
export class OrbitCamera {
  constructor() {
    this.target = [0, 0, 0];
    this.distance = 5;
    this.azimuth = 0; // Degrees about +Y; 0 looks down -Z from +Z.
    this.elevation = 15; // Degrees above the target's horizontal plane.
    this.fovY = 35;
    this.version = 0; // Bumped on every change, so listeners can tell.
  }

  eye() {
    const az = (this.azimuth * Math.PI) / 180;
    const el = (this.elevation * Math.PI) / 180;
    const d = this.distance;
    return [
      this.target[0] + d * Math.cos(el) * Math.sin(az),
      this.target[1] + d * Math.sin(el),
      this.target[2] + d * Math.cos(el) * Math.cos(az),
    ];
  }

  /** Frames a sphere of `radius` about `center`. */
  frame(center, radius) {
    this.target = center.slice();
    this.distance = (radius / Math.sin((this.fovY * Math.PI) / 360)) * 1.05;
    this.minDistance = radius * 0.02;
    this.maxDistance = this.distance * 20;
    this.changed();
  }

  changed() {
    this.version++;
  }

  view() {
    return lookAt(this.eye(), this.target, [0, 1, 0]);
  }

  /** The near and far clip distances the projection uses. */
  clip() {
    const near = Math.max(this.distance * 0.01, 1e-4);
    return { near, far: this.distance * 50 + 100 * near };
  }

  projection(aspect) {
    const { near, far } = this.clip();
    return perspective(this.fovY, aspect, near, far);
  }

  /** The camera as the server's CameraSpec. */
  spec() {
    return { position: this.eye(), target: this.target.slice(), fov_y: this.fovY };
  }

  /** Pointer and wheel handling on the canvas. */
  attach(canvas) {
    let drag = null;
    canvas.addEventListener('contextmenu', (e) => e.preventDefault());
    canvas.addEventListener('pointerdown', (e) => {
      drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 };
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener('pointerup', (e) => {
      drag = null;
      canvas.releasePointerCapture(e.pointerId);
    });
    canvas.addEventListener('pointermove', (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x;
      const dy = e.clientY - drag.y;
      drag.x = e.clientX;
      drag.y = e.clientY;
      if (drag.pan) {
        const k = (this.distance * 2 * Math.tan((this.fovY * Math.PI) / 360)) / canvas.clientHeight;
        const az = (this.azimuth * Math.PI) / 180;
        const right = [Math.cos(az), 0, -Math.sin(az)];
        this.target[0] -= right[0] * dx * k;
        this.target[2] -= right[2] * dx * k;
        this.target[1] += dy * k;
      } else {
        this.azimuth -= dx * 0.3;
        this.elevation = Math.max(-85, Math.min(85, this.elevation + dy * 0.3));
      }
      this.changed();
    });
    canvas.addEventListener(
      'wheel',
      (e) => {
        e.preventDefault();
        const f = Math.exp(e.deltaY * 0.001);
        this.distance = Math.max(this.minDistance || 1e-3, Math.min(this.maxDistance || 1e6, this.distance * f));
        this.changed();
      },
      { passive: false },
    );
  }
}
