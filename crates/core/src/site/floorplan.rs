//! The site's floor-plan image (`[floorplan]`): an image file and two
//! reference points tying its pixels to world metres, so the web map and the
//! site editor draw the grid to scale over the building's own drawing.
//!
//! Two points fix a similarity (scale, rotation, shift) from pixels to the
//! grid, and that is all a floor plan needs: an architect's drawing is to
//! scale in both directions, and its y runs down the page like the grid's
//! rows whichever way the site's world y runs (`y_axis` is undone by going
//! through grid units). The image itself is only read by those who show it
//! (`gangway check` checks it is there); a gateway serves without it.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use toml::Spanned;

/// Image formats a floor plan may be in, by file extension and content.
const FORMATS: [(&str, &str); 4] = [
    ("png", "image/png"),
    ("jpg", "image/jpeg"),
    ("jpeg", "image/jpeg"),
    ("webp", "image/webp"),
];
/// The largest floor-plan image read, bytes: a scanned A0 sheet as a JPEG.
pub const MAX_IMAGE_BYTES: u64 = 32 << 20;
/// Reference points closer than this on the image fix the scale too loosely.
const MIN_REFERENCE_PX: f64 = 10.0;

/// One reference point: where it is on the image and in the building.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferencePoint {
    /// Pixels from the image's top-left corner, x right, y down.
    pub px: [f64; 2],
    /// World metres, in the site's frame (`origin_m`, `y_axis`).
    pub m: [f64; 2],
}

/// `[floorplan]` as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct FloorplanEntry {
    image: Spanned<String>,
    reference: Spanned<Vec<ReferencePoint>>,
}

/// A validated floor plan.
#[derive(Clone, Debug, PartialEq)]
pub struct Floorplan {
    /// The image file, resolved against the site file's directory.
    pub image: PathBuf,
    /// The two reference points.
    pub reference: [ReferencePoint; 2],
    /// Pixels to grid units as an SVG matrix `(a, b, c, d, e, f)`:
    /// `gx = a·px + c·py + e`, `gy = b·px + d·py + f`.
    pub pixels_to_grid: [f64; 6],
}

impl FloorplanEntry {
    /// Checks the entry and fits pixels to grid units; `grid_of_world` is the
    /// site's frame, `dir` the site file's directory. Problems are pushed,
    /// each naming the line.
    pub(super) fn validate(
        &self,
        grid_of_world: impl Fn([f64; 2]) -> [f64; 2],
        dir: &Path,
        line_of: &dyn Fn(std::ops::Range<usize>) -> usize,
        problems: &mut Vec<String>,
    ) -> Option<Floorplan> {
        let before = problems.len();
        let image = self.image.get_ref();
        if let Err(why) = mime_of_name(image) {
            problems.push(format!(
                "line {}: `floorplan.image` {image:?}: {why}",
                line_of(self.image.span())
            ));
        }
        let line = line_of(self.reference.span());
        let points = self.reference.get_ref();
        let [a, b] = points.as_slice() else {
            problems.push(format!(
                "line {line}: `floorplan.reference` has {} points; give exactly two, each \
                 `{{ px = [x, y], m = [x, y] }}`: a spot on the image in pixels from its \
                 top-left corner and the same spot in metres",
                points.len()
            ));
            return None;
        };
        for (i, p) in points.iter().enumerate() {
            let finite = p.px.iter().chain(&p.m).all(|v| v.is_finite());
            if !finite || p.px[0] < 0.0 || p.px[1] < 0.0 {
                problems.push(format!(
                    "line {line}: `floorplan.reference` point {i}: `px` = {:?}, `m` = {:?}; \
                     pixels must be finite and not negative, metres finite",
                    p.px, p.m
                ));
            }
        }
        if problems.len() > before {
            return None;
        }
        let px_apart = (b.px[0] - a.px[0]).hypot(b.px[1] - a.px[1]);
        let m_apart = (b.m[0] - a.m[0]).hypot(b.m[1] - a.m[1]);
        if px_apart < MIN_REFERENCE_PX || m_apart < 1e-3 {
            problems.push(format!(
                "line {line}: `floorplan.reference` points are {px_apart:.1} px and \
                 {m_apart:.3} m apart; pick two spots at least {MIN_REFERENCE_PX} px apart \
                 (far apart is best: the scale is their distance)"
            ));
            return None;
        }
        Some(Floorplan {
            image: dir.join(image),
            reference: [*a, *b],
            pixels_to_grid: similarity([a.px, b.px], [grid_of_world(a.m), grid_of_world(b.m)]),
        })
    }
}

impl Floorplan {
    /// Reads the image's header: its MIME type and size in pixels, or why
    /// it cannot be shown (missing, too large, not the format its name says).
    pub fn probe(&self) -> Result<ImageInfo, String> {
        probe_image(&self.image)
    }
}

/// What [`Floorplan::probe`] found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageInfo {
    pub mime: &'static str,
    pub width: u32,
    pub height: u32,
}

/// The MIME type a floor-plan file name promises, or why it is refused.
pub fn mime_of_name(name: &str) -> Result<&'static str, String> {
    let ext = Path::new(name)
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    FORMATS
        .iter()
        .find(|(e, _)| *e == ext)
        .map(|(_, mime)| *mime)
        .ok_or_else(|| "a floor plan must be a PNG, JPEG or WebP file (.png, .jpg, .webp)".into())
}

/// The MIME type of image bytes, by their magic numbers.
pub fn mime_of_bytes(bytes: &[u8]) -> Option<&'static str> {
    match imagesize::image_type(bytes).ok()? {
        imagesize::ImageType::Png => Some("image/png"),
        imagesize::ImageType::Jpeg => Some("image/jpeg"),
        imagesize::ImageType::Webp => Some("image/webp"),
        _ => None,
    }
}

/// [`Floorplan::probe`] for any path.
pub fn probe_image(path: &Path) -> Result<ImageInfo, String> {
    let shown = path.display();
    let meta = std::fs::metadata(path)
        .map_err(|e| format!("floor-plan image {shown}: cannot read it: {e}"))?;
    if meta.len() > MAX_IMAGE_BYTES {
        return Err(format!(
            "floor-plan image {shown} is {} MiB, more than the {} MiB shown; scale it down",
            meta.len() >> 20,
            MAX_IMAGE_BYTES >> 20
        ));
    }
    let named = mime_of_name(&path.to_string_lossy())
        .map_err(|why| format!("floor-plan image {shown}: {why}"))?;
    let mut head = vec![0; 64 * 1024];
    let n = {
        use std::io::Read;
        let mut file = std::fs::File::open(path)
            .map_err(|e| format!("floor-plan image {shown}: cannot read it: {e}"))?;
        let mut n = 0;
        while n < head.len() {
            match file.read(&mut head[n..]) {
                Ok(0) => break,
                Ok(k) => n += k,
                Err(e) => return Err(format!("floor-plan image {shown}: cannot read it: {e}")),
            }
        }
        n
    };
    head.truncate(n);
    let mime = mime_of_bytes(&head)
        .filter(|m| *m == named)
        .ok_or_else(|| {
            format!("floor-plan image {shown} is not the {named} image its name says it is")
        })?;
    let size = imagesize::blob_size(&head)
        .map_err(|e| format!("floor-plan image {shown}: cannot read its size: {e}"))?;
    Ok(ImageInfo {
        mime,
        width: size.width as u32,
        height: size.height as u32,
    })
}

/// The similarity (no reflection) taking `from[0]` to `to[0]` and `from[1]`
/// to `to[1]`, as an SVG matrix: with points as complex numbers,
/// `w = s·z + t`, `s = (w1 − w0) / (z1 − z0)`, `t = w0 − s·z0`.
fn similarity(from: [[f64; 2]; 2], to: [[f64; 2]; 2]) -> [f64; 6] {
    let dz = [from[1][0] - from[0][0], from[1][1] - from[0][1]];
    let dw = [to[1][0] - to[0][0], to[1][1] - to[0][1]];
    let norm = dz[0] * dz[0] + dz[1] * dz[1];
    let sr = (dw[0] * dz[0] + dw[1] * dz[1]) / norm;
    let si = (dw[1] * dz[0] - dw[0] * dz[1]) / norm;
    let tr = to[0][0] - (sr * from[0][0] - si * from[0][1]);
    let ti = to[0][1] - (si * from[0][0] + sr * from[0][1]);
    [sr, si, -si, sr, tr, ti]
}

#[cfg(test)]
mod tests {
    use super::*;

    impl Floorplan {
        /// Grid units of a pixel of the image.
        fn grid_of_pixel(&self, [px, py]: [f64; 2]) -> [f64; 2] {
            let [a, b, c, d, e, f] = self.pixels_to_grid;
            [a * px + c * py + e, b * px + d * py + f]
        }
    }

    #[test]
    fn two_points_fix_scale_rotation_and_shift() {
        // 26 px per cell, no rotation: pixel (120, 118) is the centre of [0, 0].
        let m = similarity([[120.0, 118.0], [692.0, 482.0]], [[0.5, 0.5], [22.5, 14.5]]);
        let plan = Floorplan {
            image: PathBuf::new(),
            reference: [ReferencePoint {
                px: [0.0; 2],
                m: [0.0; 2],
            }; 2],
            pixels_to_grid: m,
        };
        let [gx, gy] = plan.grid_of_pixel([146.0, 144.0]);
        assert!((gx - 1.5).abs() < 1e-9 && (gy - 1.5).abs() < 1e-9);
        // A quarter turn: x on the image is y on the grid.
        let m = similarity([[0.0, 0.0], [10.0, 0.0]], [[0.0, 0.0], [0.0, 5.0]]);
        let plan = Floorplan {
            pixels_to_grid: m,
            ..plan
        };
        let [gx, gy] = plan.grid_of_pixel([4.0, 2.0]);
        assert!(
            (gx + 1.0).abs() < 1e-9 && (gy - 2.0).abs() < 1e-9,
            "{gx} {gy}"
        );
    }

    #[test]
    fn names_and_contents_must_agree() {
        assert_eq!(mime_of_name("plan.JPG"), Ok("image/jpeg"));
        assert!(mime_of_name("plan.svg").is_err());
        let dir = tempfile::tempdir().unwrap();
        let fake = dir.path().join("plan.png");
        std::fs::write(&fake, b"<html>not a png</html>").unwrap();
        let err = probe_image(&fake).unwrap_err();
        assert!(err.contains("is not the image/png image"), "{err}");
        let err = probe_image(&dir.path().join("missing.png")).unwrap_err();
        assert!(err.contains("cannot read it"), "{err}");
    }
}
