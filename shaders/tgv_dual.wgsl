// Dual step of the TGV primal-dual iteration, one invocation per free cube c.
// CPU twin: `gpu::twins::tgv_dual` (same name, same arithmetic order); host side: `gpu::tgv`.
//
// Reads the extrapolated primal `bar` (free cubes, then frozen neighbours) through the gather
// list of D's rows, moves p and q along K and projects them onto their unit balls, then writes
// the cube's three packed dual rows (alpha1 p_axis, alpha0 Q[axis][0..3]) for the primal step.

struct Params {
    n: u32,
    lambda: f32,
    // Invocations per row of the 2-D dispatch: c = id.x + id.y * row_stride.
    row_stride: u32,
    _padding: u32,
}

struct Gather {
    index: u32,
    weight: f32,
}

struct DualConstants {
    // sigma_p alpha1 per axis; w: alpha1.
    sigma_p: vec4<f32>,
    // sigma_q alpha0 for the diagonal rows of E'; w: alpha0.
    sigma_q_diag: vec4<f32>,
    // sigma_q alpha0 for the off-diagonal rows; w unused.
    sigma_q_off: vec4<f32>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> bar: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> row_start: array<u32>;
@group(0) @binding(3) var<storage, read> row_terms: array<Gather>;
@group(0) @binding(4) var<storage, read> constants: array<DualConstants>;
@group(0) @binding(5) var<storage, read_write> p: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> q_diag: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> q_off: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> rows: array<vec4<f32>>;

const SQRT_HALF: f32 = 0.70710678118654752440;

fn unit_ball_scale(squared_norm: f32) -> f32 {
    return 1.0 / max(sqrt(squared_norm), 1.0);
}

fn sum3(x: vec4<f32>) -> f32 {
    return x.x * x.x + x.y * x.y + x.z * x.z;
}

// D along one axis of every component of (u, v0, v1, v2).
fn difference(row: u32, centre: vec4<f32>) -> vec4<f32> {
    var acc = vec4<f32>(0.0);
    let end = row_start[row + 1u];
    for (var t = row_start[row]; t < end; t++) {
        let term = row_terms[t];
        acc += term.weight * (bar[term.index] - centre);
    }
    return acc;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let c = id.x + id.y * params.row_stride;
    if c >= params.n {
        return;
    }
    let centre = bar[c];
    let ax = difference(3u * c, centre);
    let ay = difference(3u * c + 1u, centre);
    let az = difference(3u * c + 2u, centre);
    // du = (D_x u, D_y u, D_z u), dv_i = (D_x v_i, D_y v_i, D_z v_i).
    let du = vec4<f32>(ax.x, ay.x, az.x, 0.0);
    let dv0 = vec4<f32>(ax.y, ay.y, az.y, 0.0);
    let dv1 = vec4<f32>(ax.z, ay.z, az.z, 0.0);
    let dv2 = vec4<f32>(ax.w, ay.w, az.w, 0.0);
    let k = constants[c];
    let v = vec4<f32>(centre.y, centre.z, centre.w, 0.0);
    let moved_p = p[c] + k.sigma_p * (du - v);
    let new_p = moved_p * unit_ball_scale(sum3(moved_p));
    p[c] = new_p;
    let diag = vec4<f32>(dv0.x, dv1.y, dv2.z, 0.0);
    let off = SQRT_HALF * vec4<f32>(dv0.y + dv1.x, dv0.z + dv2.x, dv1.z + dv2.y, 0.0);
    let moved_qd = q_diag[c] + k.sigma_q_diag * diag;
    let moved_qo = q_off[c] + k.sigma_q_off * off;
    let s = unit_ball_scale(sum3(moved_qd) + sum3(moved_qo));
    let qd = moved_qd * s;
    let qo = moved_qo * s;
    q_diag[c] = qd;
    q_off[c] = qo;
    // E'^T weights: Q = [[q0, s q3, s q4], [s q3, q1, s q5], [s q4, s q5, q2]], symmetric.
    let a1 = k.sigma_p.w;
    let a0 = k.sigma_q_diag.w;
    let o3 = SQRT_HALF * qo.x;
    let o4 = SQRT_HALF * qo.y;
    let o5 = SQRT_HALF * qo.z;
    rows[3u * c] = vec4<f32>(a1 * new_p.x, a0 * qd.x, a0 * o3, a0 * o4);
    rows[3u * c + 1u] = vec4<f32>(a1 * new_p.y, a0 * o3, a0 * qd.y, a0 * o5);
    rows[3u * c + 2u] = vec4<f32>(a1 * new_p.z, a0 * o4, a0 * o5, a0 * qd.z);
}
