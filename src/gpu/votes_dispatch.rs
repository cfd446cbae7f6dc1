//! Host side of `shaders/votes.wgsl`: a unit's cubes and histogram rows stay on the GPU while
//! every depth map that may see the unit votes into them; the rows come back once, at the end.

use glam::{DMat4, DVec3, Mat4, Vec4};
use wgpu::util::DeviceExt;

use super::{Gpu, GpuError, grid};
use crate::inputs::DepthMapSource;
use crate::kernels::votes::{BINS, Pyramid, UnitView};

/// The uniform `votes.wgsl` reads (`VoteMap` in the WGSL).
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct VoteMap {
    pub unit_to_camera: Mat4,
    pub intrinsics: Vec4,
    pub width: u32,
    pub height: u32,
    pub levels: u32,
    pub spherical: u32,
    pub weight: f32,
    pub n: u32,
    pub row_stride: u32,
    pub band_per_delta: f32,
    /// The least band, world units ([`crate::kernels::votes::band_floor`]).
    pub band_floor: f32,
    pub padding: [u32; 3],
}

pub const VOTES_SHADER: &str = include_str!("../../shaders/votes.wgsl");

/// What a map's vote reads, besides its pyramid: [`UnitView`] in the shader's layout.
pub fn vote_map(
    source: &DepthMapSource,
    world_to_camera: &DMat4,
    origin: DVec3,
    weight: f32,
    n: u32,
    band_floor: f64,
) -> VoteMap {
    let view = UnitView::new(source, world_to_camera, origin, band_floor);
    VoteMap {
        unit_to_camera: view.unit_to_camera,
        intrinsics: view.intrinsics,
        width: view.width,
        height: view.height,
        levels: 0,
        spherical: u32::from(view.spherical),
        weight,
        n,
        row_stride: 0,
        band_per_delta: view.band_per_delta,
        band_floor: view.band_floor,
        padding: [0; 3],
    }
}

pub use crate::kernels::votes::{cube_offsets, pyramid_arrays};

pub struct Pipeline {
    pipeline: wgpu::ComputePipeline,
}

impl Pipeline {
    pub fn new(device: &wgpu::Device) -> Pipeline {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("votes"),
            source: wgpu::ShaderSource::Wgsl(VOTES_SHADER.into()),
        });
        Pipeline {
            pipeline: device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("votes"),
                layout: None,
                module: &module,
                entry_point: Some("main"),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                cache: None,
            }),
        }
    }
}

/// One depth map's pyramid on the GPU, shared by the units of a group.
pub struct MapOnGpu {
    levels: wgpu::Buffer,
    depths: wgpu::Buffer,
    count: u32,
}

/// One unit's cubes and histogram rows on the GPU.
pub struct UnitOnGpu {
    origin: DVec3,
    n: u32,
    band_floor: f64,
    cubes: wgpu::Buffer,
    hist: wgpu::Buffer,
    votes: wgpu::Buffer,
    measured_distance: wgpu::Buffer,
}

/// A unit's rows read back from the GPU.
pub struct VotedRows {
    /// BINS per cube.
    pub hist: Vec<f32>,
    /// Two per cube: the weighted sum of the truncated distances, and the sum of their weights.
    pub distance: Vec<f32>,
    /// Votes cast since the upload.
    pub votes: u64,
}

impl Gpu {
    /// Uploads a pyramid.
    pub fn upload_pyramid(&self, pyramid: &Pyramid) -> Result<MapOnGpu, GpuError> {
        let (levels, depths) = pyramid_arrays(pyramid);
        self.check_binding("depth pyramid", std::mem::size_of_val(depths.as_slice()) as u64)?;
        let storage = wgpu::BufferUsages::STORAGE;
        Ok(MapOnGpu {
            levels: self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("levels"),
                contents: bytemuck::cast_slice(&levels),
                usage: storage,
            }),
            depths: self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("depths"),
                contents: bytemuck::cast_slice(&depths),
                usage: storage,
            }),
            count: levels.len() as u32,
        })
    }

    /// Cubes per uploaded batch of a unit: a batch's histogram rows, its largest binding,
    /// fit one binding. A unit with more cubes is uploaded as several batches, all resident
    /// (the memory budget bounds a unit), each voted like a unit of its own.
    pub fn vote_batch_cubes(&self) -> usize {
        (self.binding_limit() / (BINS * std::mem::size_of::<f32>()) as u64).max(1) as usize
    }

    /// Uploads a unit (or a batch of one): its cubes as offsets from `origin` with their
    /// voting radii ([`cube_offsets`]), and its histogram rows and distance sums so far. Batches of one unit share its `origin`, so they compute what the
    /// whole unit would.
    pub fn upload_unit(
        &self,
        origin: DVec3,
        cubes: &[Vec4],
        hist: &[f32],
        distance: &[f32],
        band_floor: f64,
    ) -> Result<UnitOnGpu, GpuError> {
        let n = u32::try_from(cubes.len()).map_err(|_| GpuError::TooLarge {
            what: "cube index",
            needed: cubes.len() as u64,
            limit: u64::from(u32::MAX),
        })?;
        self.check_binding("cubes", std::mem::size_of_val(cubes) as u64)?;
        self.check_binding("histograms", std::mem::size_of_val(hist) as u64)?;
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let padded = |bytes: &[u8]| -> Vec<u8> {
            let mut bytes = bytes.to_vec();
            bytes.resize(bytes.len().max(16), 0);
            bytes
        };
        let buffer = |label: &str, contents: Vec<u8>| {
            self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: &contents,
                usage,
            })
        };
        Ok(UnitOnGpu {
            origin,
            n,
            band_floor,
            cubes: buffer("cubes", padded(bytemuck::cast_slice(cubes))),
            hist: buffer("hist", padded(bytemuck::cast_slice(hist))),
            votes: buffer("votes", padded(&vec![0u8; 4 * cubes.len()])),
            measured_distance: buffer("distance", padded(bytemuck::cast_slice(distance))),
        })
    }

    /// Records one map's votes into a unit (runs at the next submission).
    pub fn vote(
        &self,
        unit: &UnitOnGpu,
        map: &MapOnGpu,
        source: &DepthMapSource,
        world_to_camera: &DMat4,
        weight: f32,
    ) -> Result<(), GpuError> {
        if unit.n == 0 {
            return Ok(());
        }
        let (groups_x, groups_y, row_stride) = grid(unit.n, self.limits.max_compute_workgroups_per_dimension);
        let uniform = VoteMap {
            levels: map.count,
            row_stride,
            ..vote_map(source, world_to_camera, unit.origin, weight, unit.n, unit.band_floor)
        };
        let uniform = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("vote map"),
            contents: bytemuck::bytes_of(&uniform),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let pipeline = &self.votes.pipeline;
        let group = self.bind(
            pipeline,
            &[
                &uniform,
                &unit.cubes,
                &map.levels,
                &map.depths,
                &unit.hist,
                &unit.votes,
                &unit.measured_distance,
            ],
        );
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("votes") });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("votes"),
                timestamp_writes: None,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(groups_x, groups_y, 1);
        }
        self.queue.submit([encoder.finish()]);
        Ok(())
    }

    /// Reads a unit's rows back.
    pub fn finish_unit(&self, unit: &UnitOnGpu) -> Result<VotedRows, GpuError> {
        let n = unit.n as usize;
        let hist_bytes = (n * BINS * std::mem::size_of::<f32>()) as u64;
        let per_cube = (n * std::mem::size_of::<u32>()) as u64;
        let distance_bytes = 2 * per_cube;
        let bytes = super::read_back(
            self,
            &[
                (&unit.hist, hist_bytes),
                (&unit.votes, per_cube),
                (&unit.measured_distance, distance_bytes),
            ],
        )?;
        let mut parts = bytes.into_iter();
        let (Some(hist), Some(votes), Some(distance)) = (parts.next(), parts.next(), parts.next()) else {
            return Err(GpuError::Readback("missing columns".into()));
        };
        let votes: Vec<u32> = bytemuck::pod_collect_to_vec(&votes);
        Ok(VotedRows {
            hist: bytemuck::pod_collect_to_vec(&hist),
            distance: bytemuck::pod_collect_to_vec(&distance),
            votes: votes.iter().map(|v| u64::from(*v)).sum(),
        })
    }
}
