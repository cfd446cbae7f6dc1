// Halo exchange between the chunks of a split TGV unit, one invocation per copied entry.
// CPU twin: `gpu::twins::halo`; host side: `gpu::tgv` (which runs it after every dual pass on
// the dual rows, and after every primal pass on `bar`).
//
// Entry `offset + j` of the destination chunk's array is entry `indices[j]` of the source
// chunk's: the values a chunk's gathers read from cubes (or rows) that another chunk owns.

struct HaloParams {
    count: u32,
    offset: u32,
    // Invocations per row of the 2-D dispatch: j = id.x + id.y * row_stride.
    row_stride: u32,
    _padding: u32,
}

@group(0) @binding(0) var<uniform> params: HaloParams;
@group(0) @binding(1) var<storage, read> source: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> indices: array<u32>;
@group(0) @binding(3) var<storage, read_write> destination: array<vec4<f32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = id.x + id.y * params.row_stride;
    if j >= params.count {
        return;
    }
    destination[params.offset + j] = source[indices[j]];
}
