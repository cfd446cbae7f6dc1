// Algorithm 1 (paper 4.4) for a batch of cubes and one depth map's mipmap pyramid: one
// invocation per cube, which adds the map's weight to one bin of its own histogram row and
// the truncated distance (times the weight, and the weight) to its own distance sums.
// CPU twin: `gpu::twins::votes` (same name, same f32 arithmetic); host side: `gpu::votes`.
//
// The CPU reference (`Pyramid::vote`) works in f64 on world coordinates. Here cubes come as
// f32 offsets from their unit's centre and the map's matrix takes unit-centre coordinates to
// the camera (composed in f64 on the host), so precision follows the unit's size and the
// camera distance, not the distance from the world origin.

struct VoteMap {
    // Unit-centre coordinates to camera coordinates (OpenCV axes), column-major.
    unit_to_camera: mat4x4<f32>,
    // Pinhole fx, fy, cx, cy (unused for spherical maps).
    intrinsics: vec4<f32>,
    width: u32,
    height: u32,
    levels: u32,
    // 1 for a 360-degree (equirectangular) map.
    spherical: u32,
    weight: f32,
    n: u32,
    row_stride: u32,
    // Distance sums' truncation band in units of delta, and its least value in world units
    // (`kernels::votes::truncated_distance`).
    band_per_delta: f32,
    band_floor: f32,
    padding0: u32,
    padding1: u32,
    padding2: u32,
}

@group(0) @binding(0) var<uniform> map: VoteMap;
// Per cube: offset from the unit centre (xyz) and voting radius r (w).
@group(0) @binding(1) var<storage, read> cubes: array<vec4<f32>>;
// Per level: (first index into `depths`, width, height, unused).
@group(0) @binding(2) var<storage, read> levels: array<vec4<u32>>;
// All levels' depths, row-major; invalid pixels are stored as -1.
@group(0) @binding(3) var<storage, read> depths: array<f32>;
@group(0) @binding(4) var<storage, read_write> hist: array<f32>;
@group(0) @binding(5) var<storage, read_write> votes: array<u32>;
// Per cube: the weighted sum of the truncated distances, then the sum of their weights.
@group(0) @binding(6) var<storage, read_write> measured_distance: array<f32>;

const TAU: f32 = 6.28318530717958647692;
const PI: f32 = 3.14159265358979323846;
const BINS: u32 = 8u;

// The bilinear depth of the level `shape` at level-pixel coordinates (x, y), or -1 where one
// of the 2 x 2 pixels around it is invalid or outside the image (a spherical map wraps in x),
// or their depths spread over more than `band` (`kernels::surface_depth`, whose
// `surface_depth_f32` is this function step for step).
fn surface_depth(shape: vec4<u32>, x: f32, y: f32, band: f32) -> f32 {
    let x0 = floor(x);
    let y0 = floor(y);
    let w = f32(shape.y);
    let h = f32(shape.z);
    var i0 = x0;
    var i1 = x0 + 1.0;
    if map.spherical == 1u {
        i0 = x0 - floor(x0 / w) * w;
        i1 = i0 + 1.0;
        if i1 >= w {
            i1 = 0.0;
        }
    }
    if !(i0 >= 0.0 && i0 < w && i1 < w && y0 >= 0.0 && y0 + 1.0 < h) {
        return -1.0;
    }
    let row0 = shape.x + u32(y0) * shape.y;
    let row1 = row0 + shape.y;
    let a = depths[row0 + u32(i0)];
    let b = depths[row0 + u32(i1)];
    let c = depths[row1 + u32(i0)];
    let e = depths[row1 + u32(i1)];
    if !(a > 0.0 && b > 0.0 && c > 0.0 && e > 0.0) {
        return -1.0;
    }
    let low = min(min(a, b), min(c, e));
    let high = max(max(a, b), max(c, e));
    if !(high - low <= band) {
        return -1.0;
    }
    let fx = x - x0;
    let fy = y - y0;
    return (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + e * fx) * fy;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let c = id.x + id.y * map.row_stride;
    if c >= map.n {
        return;
    }
    let cube = cubes[c];
    let radius = cube.w;
    let local = (map.unit_to_camera * vec4<f32>(cube.xyz, 1.0)).xyz;
    var u: f32;
    var v: f32;
    var distance: f32;
    var pixels_per_unit: f32;
    if map.spherical == 1u {
        distance = length(local);
        if !(distance > 0.0) {
            return;
        }
        var azimuth = atan2(local.y, local.x);
        if azimuth < 0.0 {
            azimuth += TAU;
        }
        let elevation = asin(clamp(local.z / distance, -1.0, 1.0));
        u = azimuth / TAU * f32(map.width);
        v = (PI * 0.5 - elevation) / PI * f32(map.height) - 0.5;
        pixels_per_unit = f32(map.width) / TAU / distance;
    } else {
        if !(local.z > 0.0) {
            return;
        }
        distance = local.z;
        u = map.intrinsics.x * local.x / local.z + map.intrinsics.z;
        v = map.intrinsics.y * local.y / local.z + map.intrinsics.w;
        pixels_per_unit = max(map.intrinsics.x, map.intrinsics.y) / distance;
    }
    let footprint = 2.0 * radius * pixels_per_unit;
    var level = 0u;
    if footprint > 1.0 {
        level = firstLeadingBit(u32(min(footprint, 2147483648.0)));
    }
    level = min(level, map.levels - 1u);
    let shape = levels[level];
    let scale = f32(1u << level);
    // Level-pixel coordinates, pixel centres at integers.
    let x_level = (u - (scale - 1.0) * 0.5) / scale;
    let y_level = (v - (scale - 1.0) * 0.5) / scale;
    var i = floor(x_level + 0.5);
    let j = floor(y_level + 0.5);
    let width = f32(shape.y);
    if map.spherical == 1u {
        i = i - floor(i / width) * width;
    }
    if i < 0.0 || j < 0.0 || i >= width || j >= f32(shape.z) {
        return;
    }
    let depth = depths[shape.x + u32(j) * shape.y + u32(i)];
    if !(depth > 0.0) {
        return;
    }
    let delta = 6.0 * radius;
    let eta = 3.0 * delta;
    let a = depth - distance;
    if a < -eta {
        return;
    }
    let bin = min(u32((clamp(a / delta, -1.0, 1.0) + 1.0) / 2.0 * 8.0), BINS - 1u);
    hist[c * BINS + bin] += map.weight;
    let band = max(map.band_per_delta * delta, map.band_floor);
    // The distance measures the surface where the centre projects, not the nearest pixel.
    let surface = surface_depth(shape, x_level, y_level, band);
    let measured = surface - distance;
    if surface > 0.0 && measured >= -band {
        measured_distance[2u * c] += map.weight * min(measured, band);
        measured_distance[2u * c + 1u] += map.weight;
    }
    votes[c] += 1u;
}
