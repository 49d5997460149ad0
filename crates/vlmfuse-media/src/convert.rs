//! Decoded picture → packed RGB24 at the requested size, with one cached swscale context.

use ff::ffi;
use ff::format::Pixel;
use ff::frame;
use ff::software::scaling;
use ffmpeg_next as ff;

use crate::{FrameSize, MediaError, MAX_OUTPUT_SIDE};

/// The output size for a `w`x`h` picture.
///
/// A short-side resize keeps the aspect ratio up to [`MAX_OUTPUT_SIDE`] on the long side and
/// squeezes beyond it: the models crop a square from the centre anyway, and an uncapped 8192x16
/// clip at a short side of 224 would be 77 MB of RGB per frame.
pub(crate) fn output_size(size: FrameSize, w: u32, h: u32) -> (u32, u32) {
    match size {
        FrameSize::Native => (w, h),
        FrameSize::Exact { width, height } => (width, height),
        FrameSize::ShortSide(n) => {
            let scale = |long: u32, short: u32| {
                let v = (f64::from(long) * f64::from(n) / f64::from(short.max(1))).round();
                v.clamp(f64::from(n.max(1)), f64::from(MAX_OUTPUT_SIDE.max(n))) as u32
            };
            if w <= h {
                (n, scale(h, w))
            } else {
                (scale(w, h), n)
            }
        }
    }
}

/// Everything a swscale context is specific to; a change (rare: resolution switches in
/// adaptive streams) needs a new one.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
struct Key {
    format: Pixel,
    width: u32,
    height: u32,
    out_width: u32,
    out_height: u32,
    colorspace: i32,
    full_range: bool,
}

/// Converts frames to RGB24, reusing the scaler and its output buffer across frames: building
/// a swscale context computes filter tables, which costs more than converting one small frame.
pub(crate) struct Converter {
    size: FrameSize,
    scaler: Option<(Key, scaling::Context)>,
    out: frame::Video,
}

impl Converter {
    pub(crate) fn new(size: FrameSize) -> Self {
        Converter {
            size,
            scaler: None,
            out: frame::Video::empty(),
        }
    }

    /// Returns `(width, height, rgb)` with `rgb` packed row by row without padding.
    pub(crate) fn convert(
        &mut self,
        src: &frame::Video,
    ) -> Result<(u32, u32, Vec<u8>), MediaError> {
        let (w, h) = (src.width(), src.height());
        if w == 0 || h == 0 || src.format() == Pixel::None {
            return Err(MediaError::Corrupt(
                "decoder produced an empty picture".into(),
            ));
        }
        let (out_width, out_height) = output_size(self.size, w, h);
        let key = Key {
            format: src.format(),
            width: w,
            height: h,
            out_width,
            out_height,
            colorspace: sws_colorspace(src.color_space()),
            full_range: src.color_range() == ff::color::Range::JPEG || is_yuvj(src.format()),
        };
        if self.scaler.as_ref().map(|(k, _)| *k) != Some(key) {
            let mut ctx = scaling::Context::get(
                key.format,
                w,
                h,
                Pixel::RGB24,
                out_width,
                out_height,
                scaling::Flags::BILINEAR,
            )
            .map_err(|e| {
                MediaError::Internal(format!(
                    "no scaler from {:?} {w}x{h} to RGB24 {out_width}x{out_height}: {e}",
                    key.format
                ))
            })?;
            if is_yuv(key.format) {
                // swscale assumes BT.601 limited range unless told; HD footage is usually
                // BT.709, and phones often write full range, so pass what the stream says.
                // SAFETY: `ctx` is a live SwsContext; the coefficient tables are static.
                unsafe {
                    ffi::sws_setColorspaceDetails(
                        ctx.as_mut_ptr(),
                        ffi::sws_getCoefficients(key.colorspace),
                        i32::from(key.full_range),
                        ffi::sws_getCoefficients(ffi::SWS_CS_DEFAULT),
                        1,
                        0,
                        1 << 16,
                        1 << 16,
                    );
                }
            }
            self.scaler = Some((key, ctx));
            self.out = frame::Video::empty();
        }
        let Some((_, scaler)) = self.scaler.as_mut() else {
            return Err(MediaError::Internal("scaler missing".into()));
        };
        scaler
            .run(src, &mut self.out)
            .map_err(|e| MediaError::Internal(format!("scaling failed: {e}")))?;

        let row = out_width as usize * 3;
        let stride = self.out.stride(0);
        let data = self.out.data(0);
        let rows = out_height as usize;
        if stride < row || data.len() < stride * (rows - 1) + row {
            return Err(MediaError::Internal(
                "scaler output smaller than expected".into(),
            ));
        }
        let mut rgb = Vec::with_capacity(row * rows);
        for y in 0..rows {
            rgb.extend_from_slice(&data[y * stride..y * stride + row]);
        }
        Ok((out_width, out_height, rgb))
    }
}

fn sws_colorspace(space: ff::color::Space) -> i32 {
    use ff::color::Space;
    match space {
        Space::BT709 => ffi::SWS_CS_ITU709,
        Space::FCC => ffi::SWS_CS_FCC,
        Space::SMPTE240M => ffi::SWS_CS_SMPTE240M,
        Space::BT2020NCL | Space::BT2020CL => ffi::SWS_CS_BT2020,
        _ => ffi::SWS_CS_DEFAULT,
    }
}

fn pix_name(format: Pixel) -> String {
    format
        .descriptor()
        .map(|d| d.name().to_string())
        .unwrap_or_default()
}

fn is_yuv(format: Pixel) -> bool {
    pix_name(format).starts_with("yuv")
}

/// The deprecated "JPEG range" YUV formats (MJPEG decodes to them) are full range by
/// definition, whatever the frame's range field says.
fn is_yuvj(format: Pixel) -> bool {
    pix_name(format).starts_with("yuvj")
}
