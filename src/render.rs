//! A small z-buffered software renderer for previews (`demo.png`, `octstore render`).

use glam::{Vec3, Vec3Swizzles};

use crate::stages::extract::Mesh;

/// Renders the mesh shaded (Lambert, two-sided) from a fixed 3/4 view, fitted to its bounds.
pub fn render(mesh: &Mesh, width: u32, height: u32) -> image::RgbImage {
    let mut image = image::RgbImage::from_pixel(width, height, image::Rgb([250, 250, 252]));
    if mesh.positions.is_empty() {
        return image;
    }
    let (lo, hi) = mesh
        .positions
        .iter()
        .fold((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)), |(lo, hi), p| {
            (lo.min(Vec3::from(*p)), hi.max(Vec3::from(*p)))
        });
    let center = (lo + hi) * 0.5;
    let radius = ((hi - lo).length() * 0.5).max(1e-9);
    // Camera: from the front-right, above, looking at the centre; z up.
    let forward = Vec3::new(-0.6, 0.75, -0.45).normalize();
    let right = forward.cross(Vec3::Z).normalize();
    let up = right.cross(forward);
    let scale = 0.95 * width.min(height) as f32 * 0.5 / radius;
    let light = (-forward + up * 0.6 + right * 0.3).normalize();
    let project = |p: Vec3| -> Vec3 {
        let d = p - center;
        Vec3::new(
            width as f32 * 0.5 + d.dot(right) * scale,
            height as f32 * 0.5 - d.dot(up) * scale,
            d.dot(forward),
        )
    };
    let mut depth = vec![f32::MAX; (width * height) as usize];
    for t in &mesh.triangles {
        let p = t.map(|i| Vec3::from(mesh.positions[i as usize]));
        let normal = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
        let shade = 0.25 + 0.75 * normal.dot(light).abs();
        let s = p.map(project);
        let (min, max) = (s[0].min(s[1]).min(s[2]), s[0].max(s[1]).max(s[2]));
        let area = (s[1].xy() - s[0].xy()).perp_dot(s[2].xy() - s[0].xy());
        if area.abs() < 1e-12 {
            continue;
        }
        let (x0, x1) = (min.x.floor().max(0.0) as u32, (max.x.ceil() as u32).min(width - 1));
        let (y0, y1) = (min.y.floor().max(0.0) as u32, (max.y.ceil() as u32).min(height - 1));
        for y in y0..=y1 {
            for x in x0..=x1 {
                let q = glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                let w0 = (s[2].xy() - s[1].xy()).perp_dot(q - s[1].xy()) / area;
                let w1 = (s[0].xy() - s[2].xy()).perp_dot(q - s[2].xy()) / area;
                let w2 = 1.0 - w0 - w1;
                if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                    continue;
                }
                let z = w0 * s[0].z + w1 * s[1].z + w2 * s[2].z;
                let slot = &mut depth[(y * width + x) as usize];
                if z < *slot {
                    *slot = z;
                    let c = (shade * 255.0) as u8;
                    image.put_pixel(x, y, image::Rgb([c, (shade * 235.0) as u8, (shade * 200.0) as u8]));
                }
            }
        }
    }
    image
}
