//! The cluster verbs: `plan`, `work`, `commit` (one step each, any scheduler) and `slurm`
//! (the whole chain as Slurm jobs).

use std::path::PathBuf;
use std::time::Instant;

use super::args::{CommitArgs, GlobalOptions, PlanArgs, SlurmArgs, WorkArgs};
use super::error::Result;
use super::report::{peak_rss_bytes, print_extract_summary, summary};
use super::run_options;
use crate::pipeline::cluster::{self, EXTRACT, SlurmOptions};
use crate::pipeline::{io_error, open_gpu, required_scene};
use crate::stages::extract::ExtractOptions;
use crate::store::Store;
use crate::store::cluster::ClusterPlan;

pub(super) fn plan(args: PlanArgs) -> Result<()> {
    let store = Store::open(&args.store)?;
    if args.stage == EXTRACT {
        let output = args.output.unwrap_or_else(|| PathBuf::from("mesh.ply"));
        let output = std::path::absolute(&output).map_err(io_error("resolve", &output))?;
        let options = ExtractOptions {
            region: args.region,
            simplify: super::args::simplify_of(args.decimate, args.max_error),
            surface: super::args::surface_of(args.closed, args.open),
        };
        let (plan, cubes) = cluster::plan_extract(&store, args.chunks, options, output.clone())?;
        println!(
            "plan extract: {} unit(s) in {} chunk(s) at version {} -> {}",
            plan.units.len(),
            plan.chunks,
            plan.base_version,
            output.display()
        );
        print_chunks(&plan, &cubes);
        return Ok(());
    }
    // The plan records the decided method, never `auto`: every worker runs the same one.
    let (params, method) = (args.solver.params(), args.solver.method().resolve(&store.latest()?)?);
    let runnable = cluster::cluster_stage(&store, &args.stage, params, method, None)?;
    let (plan, cubes) = store.plan_cluster_run(
        runnable.as_ref(),
        args.chunks,
        crate::store::catalog::encode(&(params, method)),
    )?;
    println!(
        "plan {}: {} pending unit(s) in {} chunk(s), base version {}, target {}",
        args.stage,
        plan.units.len(),
        plan.chunks,
        plan.base_version,
        plan.target()
    );
    print_chunks(&plan, &cubes);
    Ok(())
}

/// Prints each chunk's units and cubes, then the chunk with the most cubes: the stage's
/// critical path when every worker runs at the same rate per cube, which the stage's time on
/// one process (or the rates of BENCHMARKS.md) turns into seconds. `cubes` are the plan's
/// units' cubes in plan order.
fn print_chunks(plan: &ClusterPlan, cubes: &[u64]) {
    let mut units_before = 0;
    let mut chunk_cubes = Vec::with_capacity(plan.chunks as usize);
    for chunk in 0..plan.chunks {
        let units = plan.chunk_units(chunk).len();
        let sum: u64 = cubes.iter().skip(units_before).take(units).sum();
        units_before += units;
        chunk_cubes.push(sum);
        println!("  chunk {chunk}: {units} unit(s), {sum} cubes");
    }
    let total: u64 = chunk_cubes.iter().sum();
    let Some((largest, &most)) = chunk_cubes
        .iter()
        .enumerate()
        .max_by_key(|&(i, c)| (*c, std::cmp::Reverse(i)))
    else {
        return;
    };
    if total == 0 {
        return;
    }
    let share = |cubes: f64| 100.0 * cubes / total as f64;
    println!(
        "  critical path: chunk {largest}, {most} of the stage's {total} cubes: {:.1} % of its time on one worker \
         (an even split: {:.1} %)",
        share(most as f64),
        share(total as f64 / f64::from(plan.chunks.max(1))),
    );
}

pub(super) fn work(args: WorkArgs) -> Result<()> {
    let store = Store::open_read_only(&args.store)?;
    let started = Instant::now();
    let mut on_device = String::new();
    let report = if args.stage == EXTRACT {
        cluster::work_extract(&store, args.chunk)?
    } else {
        let gpu = open_gpu(args.device)?;
        let runnable = cluster::stage_of_plan(&store, &args.stage, gpu.clone())?;
        let report = store.work_cluster_chunk(runnable.as_ref(), args.chunk)?;
        if let Some(gpu) = gpu {
            let (units, fallbacks) = gpu.counts();
            on_device = format!(" ({units} on {}, {fallbacks} fell back to the CPU)", gpu.adapter.name);
        }
        report
    };
    println!(
        "work {} chunk {}: {} unit(s){on_device}, {} already done | {:.2}s | peak memory {:.0} MB",
        args.stage,
        args.chunk,
        report.units,
        report.skipped,
        started.elapsed().as_secs_f64(),
        peak_rss_bytes() as f64 / 1e6
    );
    Ok(())
}

pub(super) fn commit(global: &GlobalOptions, args: CommitArgs) -> Result<()> {
    let store = Store::open(&args.store)?;
    if args.stage == EXTRACT {
        let started = Instant::now();
        let (summary, output) = cluster::commit_extract(&store, global.memory_budget)?;
        print_extract_summary(&summary, &output, started);
        return Ok(());
    }
    let runnable = cluster::stage_of_plan(&store, &args.stage, None)?;
    let report = store.commit_cluster_run(runnable.as_ref(), &run_options(global, false))?;
    summary(&report);
    Ok(())
}

pub(super) fn slurm(global: &GlobalOptions, args: SlurmArgs) -> Result<()> {
    let store = args.store;
    let opened = Store::open_read_only(&store)?;
    let scene = required_scene(&opened, "slurm")?;
    // The jobs name the decided method: `auto` decided once, here, from the ingested maps.
    let method = args.solver.method().resolve(&opened.latest()?)?;
    drop(opened);
    let options = SlurmOptions {
        chunks: args.chunks,
        partition: args.partition,
        sbatch_args: args.sbatch_args,
        binary: std::env::current_exe().map_err(io_error("locate octstore", &store))?,
        params: args.solver.params(),
        method,
        memory_budget: global.memory_budget,
        leaf_cubes: args.leaf_cubes,
        device: args.device,
        output: args
            .output
            .map(|o| std::path::absolute(&o).map_err(io_error("resolve", &o)))
            .transpose()?,
    };
    let store_path = std::path::absolute(&store).map_err(io_error("resolve", &store))?;
    let jobs = cluster::slurm_jobs(&store_path, scene.max_depth, &options);
    if args.dry_run {
        for job in &jobs {
            println!(
                "# ---- {}{}",
                job.name,
                if job.array.is_some() { " (array)" } else { "" }
            );
            println!("{}", job.script);
        }
        return Ok(());
    }
    cluster::submit_slurm_jobs(&store_path, &jobs, |name, id| println!("{name} {id}"))?;
    Ok(())
}
