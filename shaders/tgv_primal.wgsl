// Primal step of the TGV primal-dual iteration, one invocation per free cube j.
// CPU twin: `gpu::twins::tgv_primal` (same name, same arithmetic order); host side: `gpu::tgv`.
//
// Gathers K^T of the packed dual rows (own rows with the coefficient -row_sum, then the rows
// whose terms target j), takes the prox of the histogram data term for u and a plain step for
// v, and writes the extrapolation 2 x_new - x_old to `bar`.

struct Params {
    n: u32,
    lambda: f32,
    row_stride: u32,
    _padding: u32,
}

struct Gather {
    index: u32,
    weight: f32,
}

struct PrimalConstants {
    // (tau_u, tau_v0, tau_v1, tau_v2).
    tau: vec4<f32>,
    // Minus the coefficient of the cube itself in its rows of D, per axis; w unused.
    own: vec4<f32>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> rows: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> col_start: array<u32>;
@group(0) @binding(3) var<storage, read> col_terms: array<Gather>;
@group(0) @binding(4) var<storage, read> constants: array<PrimalConstants>;
// The data term's 9 slopes per cube (`tgv::Slopes`), packed.
@group(0) @binding(5) var<storage, read> slopes: array<f32>;
@group(0) @binding(6) var<storage, read_write> uv: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> bar: array<vec4<f32>>;

// prox of tau lambda sum_b h_b |u - f_b|, clamped to [-1, 1]: the sum of the 9 clamps of
// u + tau lambda slope_i to the interval between bin centres i - 1 and i (`tgv::prox_slopes`).
fn prox_slopes(u: f32, tau_lambda: f32, c: u32) -> f32 {
    let base = 9u * c;
    let first = u + tau_lambda * vec4<f32>(slopes[base], slopes[base + 1u], slopes[base + 2u], slopes[base + 3u]);
    let second = u + tau_lambda * vec4<f32>(slopes[base + 4u], slopes[base + 5u], slopes[base + 6u], slopes[base + 7u]);
    let c_first = vec4<f32>(
        min(first.x, -0.875),
        min(max(first.y, -0.875), -0.625),
        min(max(first.z, -0.625), -0.375),
        min(max(first.w, -0.375), -0.125),
    );
    let c_second = min(max(second, vec4<f32>(-0.125, 0.125, 0.375, 0.625)), vec4<f32>(0.125, 0.375, 0.625, 0.875));
    let last = max(u + tau_lambda * slopes[base + 8u], 0.875);
    let pair = c_first + c_second;
    let sum = (pair.x + pair.y) + (pair.z + pair.w) + last;
    return min(max(sum, -1.0), 1.0);
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = id.x + id.y * params.row_stride;
    if j >= params.n {
        return;
    }
    let r0 = rows[3u * j];
    let r1 = rows[3u * j + 1u];
    let r2 = rows[3u * j + 2u];
    let k = constants[j];
    var adjoint = -(k.own.x * r0 + k.own.y * r1 + k.own.z * r2);
    let end = col_start[j + 1u];
    for (var t = col_start[j]; t < end; t++) {
        let term = col_terms[t];
        adjoint += term.weight * rows[term.index];
    }
    // v's adjoint also has -alpha1 p, the first entries of the cube's own rows.
    adjoint -= vec4<f32>(0.0, r0.x, r1.x, r2.x);
    let old = uv[j];
    var new_uv = old - k.tau * adjoint;
    new_uv.x = prox_slopes(new_uv.x, k.tau.x * params.lambda, j);
    uv[j] = new_uv;
    bar[j] = 2.0 * new_uv - old;
}
