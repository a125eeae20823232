//! STUB (replaced by the image decoder branch): the API the importer calls.
use std::sync::Arc;

use crowdmorph_core::budget::Budget;
use crowdmorph_core::rig::{ImageData, ImageMime, Mips};

/// An image's format and size from its header.
pub struct ImageHeader {
    /// Format by magic.
    pub mime: ImageMime,
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
}

/// Header only.
pub fn sniff(_bytes: &[u8]) -> Result<ImageHeader, String> {
    Err("image decoding is not built yet".into())
}

/// Most bytes `decode` charges at once.
pub fn decode_cost(h: &ImageHeader, _max_texture_size: u32) -> u64 {
    Mips::chain_bytes(h.width, h.height) * 2
}

/// Decodes.
pub fn decode(
    index: usize,
    _bytes: Arc<[u8]>,
    _declared: Option<ImageMime>,
    _max_texture_size: u32,
    _budget: &Budget,
) -> Result<(ImageData, Vec<String>), ImageError> {
    Err(ImageError::Invalid {
        index,
        problem: "not built".into(),
    })
}

/// Rebuilds pixels.
pub fn decode_pixels(
    index: usize,
    _image: &ImageData,
    _budget: &Budget,
) -> Result<Arc<Mips>, ImageError> {
    Err(ImageError::Invalid {
        index,
        problem: "not built".into(),
    })
}

/// Why an image is refused.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// Unusable.
    #[error("image {index}: {problem}")]
    Invalid {
        /// Image index.
        index: usize,
        /// What.
        problem: String,
    },
    /// Over budget.
    #[error(transparent)]
    Budget(#[from] crowdmorph_core::budget::BudgetError),
}
