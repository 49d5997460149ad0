//! Decoded video frames, as the media layer produces them and every model consumes them.
//!
//! One type for both ends: the media crate used to return its own frame (`pts_s`) and the models
//! crate took another (`t_s`), so the service copied every frame between two spellings of the
//! same thing. Defined here rather than in the media crate so model backends can be built and
//! tested without FFmpeg.

/// Why a frame buffer cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    #[error("empty frame {width}x{height}")]
    Empty { width: u32, height: u32 },
    #[error("frame {width}x{height} needs {want} RGB bytes, got {got}")]
    WrongLength {
        width: u32,
        height: u32,
        want: usize,
        got: usize,
    },
}

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
    pub fn validate(&self) -> Result<(), FrameError> {
        let want = self.width as usize * self.height as usize * 3;
        if self.width == 0 || self.height == 0 {
            return Err(FrameError::Empty {
                width: self.width,
                height: self.height,
            });
        }
        if self.rgb.len() != want {
            return Err(FrameError::WrongLength {
                width: self.width,
                height: self.height,
                want,
                got: self.rgb.len(),
            });
        }
        Ok(())
    }
}

/// An owned frame. Reporters receive them behind an `Arc` (they may outlive the decoder's
/// buffers and move work onto other threads).
#[derive(Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// `width * height * 3` bytes, row-major, no row padding, so it can be handed to a tensor
    /// library as is.
    pub rgb: Vec<u8>,
    /// Presentation time of the frame in the clip, seconds from the start of the video stream.
    pub pts_s: f64,
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

impl std::fmt::Debug for Frame {
    // The pixel buffer is megabytes: printing it would drown any log or test failure.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Frame")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("pts_s", &self.pts_s)
            .field("rgb_len", &self.rgb.len())
            .finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_names_the_problem() {
        let f = |w, h, n| FrameRef {
            width: w,
            height: h,
            rgb: &[0u8; 12][..n],
        };
        assert!(f(2, 2, 12).validate().is_ok());
        assert!(matches!(
            f(0, 2, 0).validate(),
            Err(FrameError::Empty { .. })
        ));
        let e = f(2, 2, 5).validate().unwrap_err();
        assert!(e.to_string().contains("needs 12"), "{e}");
    }
}
