//! Frame thumbnails kept with a `/v1/infer` round for the operator page: a few evenly spaced
//! frames of those the reporters saw, shrunk to `[ui] thumbnail_width` and stored as JPEG (a
//! 192-pixel-wide frame is about 5–10 KB), so a round's page shows what was judged without
//! keeping the clip.

use vlmfuse_models::Frame;
use vlmfuse_store::browse::Thumbnail;

/// JPEG quality of a thumbnail: small files, faces and signs still recognisable.
const QUALITY: u8 = 75;

/// `count` evenly spaced frames of `frames` (first and last included), each `width` pixels wide
/// (never enlarged). A frame that cannot be encoded is skipped: thumbnails are an aid, never a
/// reason to refuse a clip.
pub fn make(frames: &[Frame], count: usize, width: u32) -> Vec<Thumbnail> {
    if count == 0 || frames.is_empty() {
        return Vec::new();
    }
    let picks: Vec<usize> = if frames.len() <= count {
        (0..frames.len()).collect()
    } else if count == 1 {
        vec![0]
    } else {
        let last = frames.len() - 1;
        let mut v: Vec<usize> = (0..count)
            .map(|j| (j * last + (count - 1) / 2) / (count - 1))
            .collect();
        v.dedup();
        v
    };
    picks
        .into_iter()
        .filter_map(|i| {
            let f = &frames[i];
            encode(f, width).map(|jpeg| Thumbnail {
                index: i as u32,
                t_s: f.pts_s,
                jpeg,
            })
        })
        .collect()
}

fn encode(f: &Frame, width: u32) -> Option<Vec<u8>> {
    let img = image::RgbImage::from_raw(f.width, f.height, f.rgb.clone())?;
    let w = width.min(f.width).max(1);
    let h = ((f.height as u64 * w as u64) / f.width.max(1) as u64).max(1) as u32;
    let small = if w == f.width {
        img
    } else {
        image::imageops::thumbnail(&img, w, h)
    };
    let mut out = Vec::new();
    let enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, QUALITY);
    small.write_with_encoder(enc).ok()?;
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(i: u32) -> Frame {
        Frame {
            width: 64,
            height: 48,
            rgb: vec![(i * 20) as u8; 64 * 48 * 3],
            pts_s: i as f64 * 0.5,
        }
    }

    #[test]
    fn evenly_spaced_small_jpegs() {
        let frames: Vec<Frame> = (0..10).map(frame).collect();
        let t = make(&frames, 4, 32);
        assert_eq!(
            t.iter().map(|t| t.index).collect::<Vec<_>>(),
            vec![0, 3, 6, 9]
        );
        assert_eq!(t[1].t_s, 1.5);
        let img = image::load_from_memory(&t[0].jpeg).unwrap();
        assert_eq!((img.width(), img.height()), (32, 24));
        assert!(make(&frames, 0, 32).is_empty());
        assert_eq!(make(&frames[..2], 4, 32).len(), 2);
        // Never enlarged.
        let big = make(&frames[..1], 1, 640);
        assert_eq!(image::load_from_memory(&big[0].jpeg).unwrap().width(), 64);
    }
}
