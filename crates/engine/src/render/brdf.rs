//! The shading model of rendered frames, on the CPU: glTF 2.0's metallic-roughness BRDF
//! (the specification's Appendix B) under the renderer's fixed lights, mirrored line for line
//! by `shaders/render.wgsl`.
//!
//! Why a CPU copy exists: the GPU picture is checked against it pixel by pixel (tests render a
//! flat quad and compare its centre with [`shade`] at the same point), and a reference renderer
//! such as three.js gets the very same lights from [`reference_lights`], so two pictures of one
//! rig differ only where the renderers really do.
//!
//! The model, per Appendix B's implementation section:
//! - `c_diff = mix(base, 0, metallic)`, `F0 = mix(0.04, base, metallic)`, `α = roughness²`;
//! - `F = F0 + (1 − F0)(1 − v·h)⁵` (Schlick), `D` GGX (Trowbridge-Reitz), `V` the
//!   height-correlated Smith visibility;
//! - `f = (1 − F) c_diff / π + F D V`, times `n·l` and each directional light's irradiance;
//! - a hemisphere ambient `mix(ground, sky, ½ + ½ n·up) · c_diff / π · occlusion` (what
//!   three.js's `HemisphereLight` adds without an environment map), plus emission;
//! - no tone mapping: the linear result is clamped by the sRGB target.
//!
//! For three.js (r155 and later, physically correct lights, `NoToneMapping`): two
//! `DirectionalLight`s of the intensities and directions [`reference_lights`] gives and a
//! `HemisphereLight` of the sky and ground colours at intensity 1 with its position along
//! `up`, the colours set as linear values (`Color.setRGB(r, g, b, LinearSRGBColorSpace)`; a hex
//! colour would be decoded from sRGB). Known differences remain: three.js does not weigh its
//! direct diffuse term by `1 − F`, so a dielectric's diffuse is up to 4 % brighter there at
//! normal incidence (more at grazing angles), and it widens roughness by the normal's
//! screen-space derivatives (specular anti-aliasing), which shows on curved, smooth surfaces.
//!
//! The lights are fixed relative to the camera (so every view of a head is lit alike) and
//! tuned so the embedded head looks as it did under the earlier Lambert + Blinn-Phong shading:
//! a key from the camera's upper left, a dimmer fill from its lower right, and a sky brighter
//! than the ground.

use glam::Vec3;

use super::scene::View;

/// Smallest roughness shaded: GGX's `D` is a Dirac pulse at 0 (a NaN at the highlight's
/// centre), so mirror-smooth materials are drawn this rough — three.js's floor too.
pub const MIN_ROUGHNESS: f32 = 0.0525;

/// Key light in view space (x right, y up, z toward the viewer): unit direction toward the
/// light before normalization, and its irradiance (`E`, linear, as three.js's
/// `DirectionalLight.intensity`). 0.75·π: the earlier Lambert key of 0.75 over a white albedo.
pub const KEY_LIGHT: ([f32; 3], f32) = ([-0.5, 0.6, 0.8], 2.4);
/// Fill light in view space, as [`KEY_LIGHT`]: from the lower right, about a third of the key.
pub const FILL_LIGHT: ([f32; 3], f32) = ([0.7, -0.2, 0.6], 0.85);
/// Hemisphere ambient: irradiance from the sky (the camera's up) and from the ground, linear
/// RGB (three.js's `HemisphereLight(sky, ground, 1)`). Their mean, 0.56, is the earlier
/// ambient of 0.18 times π. With the two lights, fitted to the earlier shading of the embedded
/// head's skin over the normals a face shows: 2.3/255 apart on average in sRGB.
pub const SKY: [f32; 3] = [0.7, 0.7, 0.7];
/// See [`SKY`].
pub const GROUND: [f32; 3] = [0.42, 0.42, 0.42];

/// One directional light in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DirectionalLight {
    /// Unit direction from the surface toward the light.
    pub direction: Vec3,
    /// Irradiance on a surface facing it (linear; white light).
    pub intensity: f32,
}

/// The lights of a view, in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lights {
    /// The key light.
    pub key: DirectionalLight,
    /// The fill light.
    pub fill: DirectionalLight,
    /// The hemisphere ambient's up (the camera's up, unit).
    pub up: Vec3,
    /// Sky irradiance, linear RGB.
    pub sky: Vec3,
    /// Ground irradiance, linear RGB.
    pub ground: Vec3,
}

/// The renderer's lights for `view`, in world space: what a reference renderer sets up to
/// compare its picture with ours (`None` when the view has no direction: the eye at the
/// target, or up along the view).
pub fn reference_lights(view: &View) -> Option<Lights> {
    let forward = (view.target - view.eye).normalize_or_zero();
    let right = forward.cross(view.up).normalize_or_zero();
    if forward == Vec3::ZERO || right == Vec3::ZERO {
        return None;
    }
    let up = right.cross(forward);
    let to_world = |v: [f32; 3]| {
        let v = Vec3::from_array(v);
        (right * v.x + up * v.y - forward * v.z).normalize()
    };
    Some(Lights {
        key: DirectionalLight {
            direction: to_world(KEY_LIGHT.0),
            intensity: KEY_LIGHT.1,
        },
        fill: DirectionalLight {
            direction: to_world(FILL_LIGHT.0),
            intensity: FILL_LIGHT.1,
        },
        up,
        sky: Vec3::from_array(SKY),
        ground: Vec3::from_array(GROUND),
    })
}

/// What a point of a surface is made of, after textures: the inputs of [`shade`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Surface {
    /// Base colour, linear RGB.
    pub base: Vec3,
    /// Metalness, 0..=1.
    pub metallic: f32,
    /// Perceptual roughness, 0..=1.
    pub roughness: f32,
    /// Ambient occlusion, 0..=1 (1: none).
    pub occlusion: f32,
    /// Emitted radiance, linear RGB.
    pub emissive: Vec3,
}

/// The BRDF of one directional light times `n·l` (the light's irradiance not included):
/// `((1 − F) c_diff / π + F D V) n·l`.
pub fn direct(n: Vec3, v: Vec3, l: Vec3, c_diff: Vec3, f0: Vec3, alpha: f32) -> Vec3 {
    let n_l = n.dot(l).clamp(0.0, 1.0);
    if n_l <= 0.0 {
        return Vec3::ZERO;
    }
    // A normal facing away from the eye (interpolated normals at a silhouette) shades as if
    // grazing rather than with a negative cosine.
    let n_v = n.dot(v).clamp(0.0, 1.0);
    let h = (l + v).normalize_or_zero();
    let n_h = n.dot(h).clamp(0.0, 1.0);
    let v_h = v.dot(h).clamp(0.0, 1.0);
    let f = f0 + (Vec3::ONE - f0) * (1.0 - v_h).powi(5);
    let a2 = alpha * alpha;
    let d_den = n_h * n_h * (a2 - 1.0) + 1.0;
    let d = a2 / (std::f32::consts::PI * d_den * d_den);
    let vis_den =
        n_l * (n_v * n_v * (1.0 - a2) + a2).sqrt() + n_v * (n_l * n_l * (1.0 - a2) + a2).sqrt();
    let vis = if vis_den > 0.0 { 0.5 / vis_den } else { 0.0 };
    ((Vec3::ONE - f) * c_diff / std::f32::consts::PI + f * (d * vis)) * n_l
}

/// The linear radiance toward the eye of `surface` at unit normal `n`, seen along unit `v`
/// (surface → eye), under `lights`.
pub fn shade(surface: &Surface, n: Vec3, v: Vec3, lights: &Lights) -> Vec3 {
    let metallic = surface.metallic.clamp(0.0, 1.0);
    let roughness = surface.roughness.clamp(MIN_ROUGHNESS, 1.0);
    let c_diff = surface.base.lerp(Vec3::ZERO, metallic);
    let f0 = Vec3::splat(0.04).lerp(surface.base, metallic);
    let alpha = roughness * roughness;
    let mut c = Vec3::ZERO;
    for light in [lights.key, lights.fill] {
        c += direct(n, v, light.direction, c_diff, f0, alpha) * light.intensity;
    }
    let sky_weight = 0.5 + 0.5 * n.dot(lights.up);
    let ambient = lights.ground.lerp(lights.sky, sky_weight);
    c += ambient * c_diff / std::f32::consts::PI * surface.occlusion;
    c + surface.emissive
}

/// A linear channel as the sRGB target stores it: clamped, encoded, rounded to 8 bits.
pub fn linear_to_srgb8(c: f32) -> u8 {
    let c = c.clamp(0.0, 1.0);
    let s = if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0).round() as u8
}

/// An 8-bit sRGB channel as a linear value (what sampling an sRGB view returns).
pub fn srgb8_to_linear(c: u8) -> f32 {
    let c = f32::from(c) / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// The base colour texture's value after its layers, as the shader's `fs_main` sums them:
/// `clamp(tex + Σ_k c_k · layer_k, 0, 1)` per linear channel (before the material factor and
/// the vertex colour multiply it). `tex` is the sampled base texture (white without one).
pub fn layered_base(tex: [f32; 4], layers: &[[f32; 4]], coefficients: &[f32]) -> [f32; 4] {
    let mut out = tex;
    for (layer, &c) in layers.iter().zip(coefficients) {
        for (o, v) in out.iter_mut().zip(layer) {
            *o += c * v;
        }
    }
    out.map(|v| v.clamp(0.0, 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view() -> View {
        View {
            eye: Vec3::new(0.0, 0.0, 5.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_deg: 30.0,
            near: 0.1,
            far: 100.0,
        }
    }

    #[test]
    fn the_lights_are_camera_relative_unit_directions() {
        let l = reference_lights(&view()).expect("a view with a direction");
        // Upper left and in front of a camera on +Z looking down −Z.
        assert!(l.key.direction.x < 0.0 && l.key.direction.y > 0.0 && l.key.direction.z > 0.0);
        assert!((l.key.direction.length() - 1.0).abs() < 1e-6);
        assert!(l.fill.direction.x > 0.0 && l.fill.direction.y < 0.0);
        assert!((l.up - Vec3::Y).length() < 1e-6);
        // Turning the camera turns the lights with it.
        let side = View {
            eye: Vec3::new(5.0, 0.0, 0.0),
            ..view()
        };
        let s = reference_lights(&side).expect("lights");
        assert!(s.key.direction.x > 0.0 && s.key.direction.z > 0.0);
        assert!(
            reference_lights(&View {
                eye: Vec3::ZERO,
                ..view()
            })
            .is_none()
        );
    }

    #[test]
    fn a_white_lambertian_limit_and_energy_are_sane() {
        let l = reference_lights(&view()).expect("lights");
        let n = Vec3::Z;
        let v = Vec3::Z;
        // Rough dielectric white: mostly diffuse, nearly (1 − 0.04) of Lambert.
        let white = Surface {
            base: Vec3::ONE,
            metallic: 0.0,
            roughness: 1.0,
            occlusion: 1.0,
            emissive: Vec3::ZERO,
        };
        let c = shade(&white, n, v, &l);
        let lambert = (l.key.intensity * n.dot(l.key.direction)
            + l.fill.intensity * n.dot(l.fill.direction))
            / std::f32::consts::PI
            + (l.sky.x + l.ground.x) * 0.5 / std::f32::consts::PI;
        assert!((c.x / lambert - 1.0).abs() < 0.08, "{c} vs {lambert}");
        // A black rough metal reflects almost nothing.
        let black_metal = Surface {
            base: Vec3::ZERO,
            metallic: 1.0,
            ..white
        };
        assert!(shade(&black_metal, n, v, &l).max_element() < 1e-3);
        // Smoothness concentrates the highlight: at the key's mirror direction, smoother is
        // brighter.
        let h = (l.key.direction + v).normalize();
        let at = |r: f32| {
            shade(
                &Surface {
                    base: Vec3::splat(0.5),
                    metallic: 1.0,
                    roughness: r,
                    ..white
                },
                h,
                v,
                &l,
            )
            .x
        };
        assert!(at(0.2) > at(0.5) && at(0.5) > at(0.9));
        // Occlusion darkens the ambient only; emission adds.
        let occluded = Surface {
            occlusion: 0.0,
            ..white
        };
        assert!(shade(&occluded, n, v, &l).x < c.x);
        let glowing = Surface {
            emissive: Vec3::new(0.25, 0.0, 0.0),
            ..white
        };
        assert!((shade(&glowing, n, v, &l).x - c.x - 0.25).abs() < 1e-6);
        // Zero roughness is floored, never NaN.
        assert!(at(0.0).is_finite());
    }

    #[test]
    fn srgb_round_trips_every_byte() {
        for b in 0..=255u8 {
            assert_eq!(linear_to_srgb8(srgb8_to_linear(b)), b);
        }
    }
}
