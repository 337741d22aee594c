//! Match pictures: the two images side by side (top-aligned) with a line per match,
//! coloured by the first keypoint's position so crossings stand out.

use dens3r_align::matching::Match;
use image::{Rgb, RgbImage};

/// Draws at most `max_lines` of `matches` (evenly subsampled) between `a` (left) and `b`.
pub fn match_picture(a: &RgbImage, b: &RgbImage, matches: &[Match], max_lines: usize) -> RgbImage {
    let (wa, ha) = a.dimensions();
    let (wb, hb) = b.dimensions();
    let mut out = RgbImage::new(wa + wb, ha.max(hb));
    image::imageops::replace(&mut out, a, 0, 0);
    image::imageops::replace(&mut out, b, wa as i64, 0);
    // Dim the photos so the lines read.
    out.pixels_mut().for_each(|p| p.0 = p.0.map(|c| c / 2 + 32));
    let step = matches.len().div_ceil(max_lines.max(1)).max(1);
    for m in matches.iter().step_by(step) {
        let c = hue(m.a.0 as f32 / wa.max(1) as f32 * 0.8 + m.a.1 as f32 / ha.max(1) as f32 * 0.2);
        let p0 = (m.a.0 as i64, m.a.1 as i64);
        let p1 = (m.b.0 as i64 + wa as i64, m.b.1 as i64);
        line(&mut out, p0, p1, c);
        for p in [p0, p1] {
            dot(&mut out, p, c);
        }
    }
    out
}

/// A saturated colour for `t` in [0, 1] (red -> yellow -> green -> cyan -> blue).
fn hue(t: f32) -> Rgb<u8> {
    let h = t.clamp(0.0, 1.0) * 4.0;
    let f = |x: f32| (x.clamp(0.0, 1.0) * 255.0) as u8;
    Rgb([f(2.0 - h), f(if h < 2.0 { h } else { 4.0 - h }), f(h - 2.0)])
}

fn put(img: &mut RgbImage, (x, y): (i64, i64), c: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, c);
    }
}

fn dot(img: &mut RgbImage, (x, y): (i64, i64), c: Rgb<u8>) {
    for dy in -1..=1 {
        for dx in -1..=1 {
            put(img, (x + dx, y + dy), c);
        }
    }
}

/// Bresenham's line.
fn line(img: &mut RgbImage, (mut x0, mut y0): (i64, i64), (x1, y1): (i64, i64), c: Rgb<u8>) {
    let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
    let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
    let mut err = dx + dy;
    loop {
        put(img, (x0, y0), c);
        if x0 == x1 && y0 == y1 {
            break;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x0 += sx;
        }
        if e2 <= dx {
            err += dx;
            y0 += sy;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_join_the_matched_pixels() {
        let a = RgbImage::from_pixel(20, 10, Rgb([0, 0, 0]));
        let b = RgbImage::from_pixel(30, 16, Rgb([0, 0, 0]));
        let m = Match { a: (2, 3), b: (25, 14), conf: 2.0 };
        let img = match_picture(&a, &b, &[m], 10);
        assert_eq!(img.dimensions(), (50, 16));
        let lit = |x: u32, y: u32| img.get_pixel(x, y).0 != [32, 32, 32];
        assert!(lit(2, 3) && lit(45, 14), "both end points are drawn");
        // The line passes through its midpoint and the background elsewhere stays dim.
        assert!(lit((2 + 45) / 2, (3 + 14) / 2) || lit((2 + 45) / 2 + 1, (3 + 14) / 2));
        assert!(!lit(10, 14) && !lit(40, 1));
    }
}
