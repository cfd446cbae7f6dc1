//! A small z-buffered software renderer for previews (`demo.png`, `octstore render`).

use glam::{Vec3, Vec3Swizzles};

use super::Mesh;

/// Where the picture is taken from.
#[derive(Clone, Copy, Debug)]
pub enum View {
    /// Orthographic, from a fixed 3/4 direction (front-right, above, z up), fitted to the
    /// mesh's bounds.
    Fitted,
    /// A pinhole camera with OpenCV axes (x right, y down, z forward), its principal point at
    /// the image centre: the same picture for every mesh given the same pose, so that meshes
    /// from different methods can be compared side by side.
    Pinhole {
        /// Camera-to-world pose.
        camera_to_world: glam::DMat4,
        /// Focal length in pixels.
        focal: f64,
    },
}

/// Renders the mesh shaded (Lambert, two-sided) from a fixed 3/4 view, fitted to its bounds.
pub fn render(mesh: &Mesh, width: u32, height: u32) -> image::RgbImage {
    render_view(mesh, width, height, View::Fitted)
}

/// Renders the mesh shaded (Lambert, two-sided) from `view`.
pub fn render_view(mesh: &Mesh, width: u32, height: u32, view: View) -> image::RgbImage {
    let mut image = image::RgbImage::from_pixel(width, height, image::Rgb([250, 250, 252]));
    if mesh.positions.is_empty() || width == 0 || height == 0 {
        return image;
    }
    // Each view maps a world point to (pixel x, pixel y, depth), depth smaller when nearer and
    // affine in screen space (1/z for the pinhole), and gives the light direction.
    let project: Box<dyn Fn(Vec3) -> Option<Vec3>>;
    let light: Vec3;
    match view {
        View::Fitted => {
            let (lo, hi) = mesh
                .positions
                .iter()
                .fold((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)), |(lo, hi), p| {
                    (lo.min(Vec3::from(*p)), hi.max(Vec3::from(*p)))
                });
            let center = (lo + hi) * 0.5;
            let radius = ((hi - lo).length() * 0.5).max(1e-9);
            let forward = Vec3::new(-0.6, 0.75, -0.45).normalize();
            let right = forward.cross(Vec3::Z).normalize();
            let up = right.cross(forward);
            let scale = 0.95 * width.min(height) as f32 * 0.5 / radius;
            light = (-forward + up * 0.6 + right * 0.3).normalize();
            project = Box::new(move |p: Vec3| {
                let d = p - center;
                Some(Vec3::new(
                    width as f32 * 0.5 + d.dot(right) * scale,
                    height as f32 * 0.5 - d.dot(up) * scale,
                    d.dot(forward),
                ))
            });
        }
        View::Pinhole { camera_to_world, focal } => {
            let world_to_camera = camera_to_world.inverse().as_mat4();
            let focal = focal as f32;
            // A headlight, slightly above the camera.
            light = (camera_to_world.transform_vector3(glam::DVec3::new(0.0, -0.3, -1.0)))
                .as_vec3()
                .normalize_or_zero();
            project = Box::new(move |p: Vec3| {
                let c = world_to_camera.transform_point3(p);
                (c.z > 1e-3).then(|| {
                    Vec3::new(
                        width as f32 * 0.5 + focal * c.x / c.z,
                        height as f32 * 0.5 + focal * c.y / c.z,
                        -1.0 / c.z,
                    )
                })
            });
        }
    }
    let mut depth = vec![f32::MAX; (width * height) as usize];
    for t in &mesh.triangles {
        let Some(p) = t
            .iter()
            .map(|&i| mesh.positions.get(i as usize).map(|p| Vec3::from(*p)))
            .collect::<Option<Vec<Vec3>>>()
        else {
            continue;
        };
        let [p0, p1, p2] = [p[0], p[1], p[2]];
        let normal = (p1 - p0).cross(p2 - p0).normalize_or_zero();
        let shade = 0.25 + 0.75 * normal.dot(light).abs();
        let (Some(s0), Some(s1), Some(s2)) = (project(p0), project(p1), project(p2)) else {
            continue;
        };
        let s = [s0, s1, s2];
        let (min, max) = (s0.min(s1).min(s2), s0.max(s1).max(s2));
        if max.x < 0.0 || max.y < 0.0 || min.x >= width as f32 || min.y >= height as f32 {
            continue;
        }
        let area = (s1.xy() - s0.xy()).perp_dot(s2.xy() - s0.xy());
        if area.abs() < 1e-12 {
            continue;
        }
        let (x0, x1) = (
            min.x.floor().max(0.0) as u32,
            (max.x.ceil().max(0.0) as u32).min(width - 1),
        );
        let (y0, y1) = (
            min.y.floor().max(0.0) as u32,
            (max.y.ceil().max(0.0) as u32).min(height - 1),
        );
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
                let Some(slot) = depth.get_mut((y * width + x) as usize) else {
                    continue;
                };
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A square of side 1 at distance 2 in front of a camera at the origin looking down +z,
    /// and a second one behind it: the pinhole view sees the square's image (half the focal
    /// length on each side of the centre), background outside it, and nothing of what lies
    /// behind the camera.
    #[test]
    fn pinhole_view_sees_what_the_camera_sees() {
        let square = |z: f32| -> Vec<[f32; 3]> { vec![[-0.5, -0.5, z], [0.5, -0.5, z], [0.5, 0.5, z], [-0.5, 0.5, z]] };
        let mesh = Mesh {
            positions: [square(2.0), square(-2.0)].concat(),
            normals: vec![[0.0, 0.0, -1.0]; 8],
            triangles: vec![[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]],
        };
        let view = View::Pinhole {
            camera_to_world: glam::DMat4::IDENTITY,
            focal: 100.0,
        };
        let image = render_view(&mesh, 200, 200, view);
        let background = image::Rgb([250, 250, 252]);
        assert_ne!(*image.get_pixel(100, 100), background);
        // The square spans 100 +- 25 pixels.
        assert_ne!(*image.get_pixel(78, 122), background);
        assert_eq!(*image.get_pixel(70, 100), background);
        assert_eq!(*image.get_pixel(100, 130), background);
        // Turned around, the camera sees the other square in the same place.
        let turned = glam::DMat4::from_rotation_y(std::f64::consts::PI);
        let behind = render_view(
            &mesh,
            200,
            200,
            View::Pinhole {
                camera_to_world: turned,
                focal: 100.0,
            },
        );
        assert_ne!(*behind.get_pixel(100, 100), background);
        assert_eq!(*behind.get_pixel(70, 100), background);
        // The fitted view frames both.
        assert!(render(&mesh, 200, 200).pixels().any(|p| *p != background));
    }
}
