//! Rendered frames: the picture of a crowd that clients without a mesh renderer ask for
//! (`POST /v1/crowd/render`, session viewers that want frames, `crowdmorph render`).
//!
//! | module | what it is |
//! |---|---|
//! | [`scene`] | lays a crowd out (placements, the grid, the camera), every number checked |
//! | [`cost`] | what a render costs, estimated before any work, for the render budgets |
//! | [`crowd`] | the rendering device, and drawing a planned crowd (clones as instances) |
//! | [`gpu`] | the wgpu renderer: instanced draws in passes, MSAA, reversed-Z, readback |
//! | [`appearance`] | a rig's textures, samplers and static vertex attributes on the renderer's device |
//! | [`brdf`] | the shading model and its lights on the CPU: the shader's mirror, for tests and reference renderers |
//! | [`encode`] | PNG, JPEG or raw RGBA from the read-back pixels |
//! | [`offline`] | a crowd of a rig drawn to a file, outside the server (`crowdmorph render`) |
//!
//! The deterministic CPU rasterizer of LOD's image metrics is not here: it is
//! [`crate::lod::raster`].

pub mod appearance;
pub mod brdf;
pub mod cost;
pub mod crowd;
pub mod encode;
pub mod gpu;
pub mod offline;
pub mod scene;
