//! Frame types shared by embedders and reporters. Defined here rather than in the media crate so
//! model backends can be built and tested without FFmpeg.

/// A borrowed packed-RGB24 frame (`rgb.len() == width * height * 3`, rows without padding).
#[derive(Debug, Clone, Copy)]
pub struct FrameRef<'a> {
    pub width: u32,
    pub height: u32,
    pub rgb: &'a [u8],
}

impl FrameRef<'_> {
    /// Checked up front so a bad buffer from a decoder becomes an error, not an index panic deep
    /// inside resampling.
    pub fn validate(&self) -> Result<(), crate::ModelError> {
        let want = self.width as usize * self.height as usize * 3;
        if self.width == 0 || self.height == 0 {
            return Err(crate::ModelError::InvalidInput(format!(
                "empty frame {}x{}",
                self.width, self.height
            )));
        }
        if self.rgb.len() != want {
            return Err(crate::ModelError::InvalidInput(format!(
                "frame {}x{} needs {want} RGB bytes, got {}",
                self.width,
                self.height,
                self.rgb.len()
            )));
        }
        Ok(())
    }
}

/// An owned frame, as reporters receive it (they may outlive the decoder's buffers and move work
/// onto blocking threads).
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Packed RGB24 rows.
    pub rgb: Vec<u8>,
    /// Presentation time in the clip, seconds.
    pub t_s: f64,
}

impl Frame {
    pub fn as_ref(&self) -> FrameRef<'_> {
        FrameRef {
            width: self.width,
            height: self.height,
            rgb: &self.rgb,
        }
    }
}
