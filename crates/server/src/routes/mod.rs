//! The handlers, one file per resource, each in short named phases: `health` (`/healthz`,
//! `/readyz`, `/metrics`), `rigs`, `clips`, `frames` (`POST /v1/crowd/frame`), `render`
//! (`POST /v1/crowd/render`), `appearance` (a rig's materials and textures), `channels` (what a pose answer's weights and joints name), `layers` (a rig's expression layers), `lod`, `graphs` (motion graphs), `masks` and `mappings` (a rig's named masks and mappings), `joints` (a skinned rig's joint map), `loadtest`, `replicas` (a rig store shared by replicas: commits, refreshes, lookups), `sessions` (handlers, the viewer protocol,
//! the tick) and `viewer` (the browser viewer's files). They use the HTTP layer and admission;
//! nothing below them imports them.

pub mod appearance;
pub mod channels;
pub mod clips;
pub mod frames;
pub mod graphs;
pub mod health;
pub mod joints;
pub mod layers;
pub mod loadtest;
pub mod lod;
pub mod mappings;
pub mod masks;
pub mod render;
pub mod replicas;
pub mod rigs;
pub mod sessions;
pub mod viewer;
