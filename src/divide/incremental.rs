//! A `divide` into a folder that already holds a division: only the subspaces the new points
//! touch are rewritten, and the old inputs are never read again.
//!
//! The new points are counted per owner: the subspace whose core holds them, or, where no
//! subspace was (a region that held no point), the largest empty node. An owner whose core
//! would pass the limit, and every empty owner, is divided again from its points: the new
//! ones in its grown cube and the old ones in it, each read from the one subspace file whose
//! core holds it (so no point is read twice). A subspace that stays within the limit but whose
//! grown cube receives new points is rewritten as its old file plus those points. When the
//! owners divided again hold half of all the points, the root is divided afresh instead
//! ([`owners_to_divide_again`]). The new points are copied once into a binary file and
//! sorted from there into one bucket per owner in one pass, so each owner reads only its
//! own. Every file
//! written carries the folder's generation in its name; the manifest is replaced last, and the
//! replaced files are removed only after it.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;

use super::DivideError;
use super::Result;
use super::grid::{Lookup, Node};
use super::manifest::{Cube, Manifest, Subspace};
use super::subspace_files::fixed_header;
use super::{
    BLOCK_BYTES, Context, DivideOptions, DivideReport, Feed, MAX_LOOKUP_DEPTH, PointSource, STAGING, commit, io,
    progress, scan, stream,
};
use super::{PointCloudFile, PointLayout, open_point_cloud};

/// Where new points fall: an existing subspace (by index) or an empty node.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
enum Owner {
    Subspace(usize),
    Empty(Node),
}

pub(super) fn divide_more(
    sources: &[&dyn PointSource],
    dir: &Path,
    manifest: Manifest,
    options: &DivideOptions,
) -> Result<DivideReport> {
    let Manifest { subspaces, division } = manifest;
    let layout = division.layout().map_err(|e| DivideError::BadManifest {
        path: dir.join(super::MANIFEST),
        source: e.into(),
    })?;
    check_compatible(sources, dir, &division, &layout, options)?;
    let root = division.root;
    let feeds: Vec<Feed<'_>> = sources.iter().map(|&source| Feed { source, keep: None }).collect();
    let scanned = scan(&feeds, &layout, options)?;
    if scanned.points == 0 {
        return Err(DivideError::NoPoints);
    }
    if !(root.contains(scanned.low) && root.contains(scanned.high)) {
        return Err(DivideError::BeyondRoot {
            folder: dir.to_path_buf(),
            low: scanned.low,
            high: scanned.high,
            root_min: root.min,
            root_size: root.size,
        });
    }
    let feeds: Vec<Feed<'_>> = scanned.order.iter().filter_map(|&i| feeds.get(i).copied()).collect();
    let (new_core, touched) = owners_of_new_points(&feeds, &layout, &subspaces, &division, options)?;
    // Every subspace the new points touch reads them again: from one binary copy, not from the
    // inputs (a text cloud parsed once per touched subspace made adding 500,000 points to 89
    // subspaces take 16 s, where dividing everything afresh took 1 s).
    let copy = copy_of_new_points(&feeds, &layout, &dir.join(STAGING))?;
    let redo = owners_to_divide_again(&new_core, &subspaces, division.max_points, scanned.points);
    // The subspaces under an owner divided again: its own, or all of them when everything is.
    let under = |owner: &Owner| -> Vec<usize> {
        let node = match owner {
            Owner::Subspace(i) => return vec![*i],
            Owner::Empty(node) => *node,
        };
        let inside = |s: &Subspace| s.node.level >= node.level && s.node.ancestor(node.level) == node;
        (0..subspaces.len())
            .filter(|&i| subspaces.get(i).is_some_and(inside))
            .collect()
    };
    let redone: BTreeSet<usize> = redo.iter().flat_map(&under).collect();
    let appended: Vec<usize> = touched.iter().filter(|i| !redone.contains(*i)).copied().collect();
    let old_files: Vec<PointCloudFile> = subspaces
        .iter()
        .map(|s| open_point_cloud(&dir.join(&s.file)))
        .collect::<std::result::Result<_, _>>()
        .map_err(DivideError::PointCloud)?;
    let mut report = DivideReport {
        input_points: scanned.points,
        ..DivideReport::default()
    };
    let mut replaced = BTreeSet::new();
    let mut written = Vec::new();
    let mut context = Context {
        dir,
        layout: layout.clone(),
        division: &division,
        options,
        report: &mut report,
    };
    // Each owner reads the new points in its grown cube from a bucket of its own, sorted out
    // of the copy in one pass: a pass over the copy per owner made adding 500,000 points to 89
    // subspaces take 3.2 s, three times dividing everything afresh.
    let owners: Vec<Owner> = redo
        .iter()
        .copied()
        .filter(|owner| *owner != Owner::Empty(Node::ROOT))
        .chain(appended.iter().map(|&i| Owner::Subspace(i)))
        .collect();
    let owner_node = |owner: &Owner| match owner {
        Owner::Subspace(i) => subspaces.get(*i).map_or(Node::ROOT, |s| s.node),
        Owner::Empty(node) => *node,
    };
    let deepest = owners.iter().map(|o| owner_node(o).level).max().unwrap_or(0);
    let buckets = context.buckets_of_new_points(
        &copy,
        deepest,
        owners.iter().map(|o| root.grown(owner_node(o), division.overlap)),
    )?;
    let buckets: BTreeMap<Owner, PointCloudFile> = owners.into_iter().zip(buckets).collect();
    let bucket_of = |owner: &Owner| buckets.get(owner);
    for owner in &redo {
        let top = owner_node(owner);
        replaced.extend(under(owner));
        let grown = root.grown(top, division.overlap);
        // Everything divided afresh reads the whole copy.
        let new_points: &dyn PointSource = bucket_of(owner).map_or(&copy, |bucket| bucket);
        let mut top_feeds = vec![Feed {
            source: new_points,
            keep: Some(grown),
        }];
        for (subspace, file) in subspaces.iter().zip(&old_files) {
            let core = root.core(subspace.node);
            if core.meets(&grown) {
                top_feeds.push(Feed {
                    source: file,
                    keep: Some(core.intersection(&grown)),
                });
            }
        }
        let points = owner_points(owner, &subspaces, &new_core, scanned.points);
        context.divide_node(top, points, &top_feeds, &mut written)?;
    }
    for i in appended {
        let (Some(subspace), Some(file)) = (subspaces.get(i), old_files.get(i)) else {
            continue;
        };
        replaced.insert(i);
        let new = new_core.get(&Owner::Subspace(i)).copied().unwrap_or(0);
        written.push(context.appended(subspace, file, bucket_of(&Owner::Subspace(i)), new)?);
    }
    let mut all: Vec<Subspace> = subspaces
        .iter()
        .enumerate()
        .filter(|(i, _)| !replaced.contains(i))
        .map(|(_, s)| s.clone())
        .chain(written)
        .collect();
    all.sort_by_key(|s| s.node);
    let old_names: Vec<String> = replaced
        .iter()
        .filter_map(|i| subspaces.get(*i).map(|s| s.file.clone()))
        .collect();
    let mut next = division.clone();
    next.generation += 1;
    commit(dir, all, next, &mut report)?;
    for name in old_names {
        let path = dir.join(name);
        std::fs::remove_file(&path).map_err(io("remove", &path))?;
    }
    Ok(report)
}

impl Context<'_> {
    /// `subspace` rewritten as its old `file` and then its `bucket` of new points (exactly
    /// those in its grown cube), byte for byte; `new` of them lie in its core.
    fn appended(
        &mut self,
        subspace: &Subspace,
        file: &PointCloudFile,
        bucket: Option<&PointCloudFile>,
        new: u64,
    ) -> Result<Subspace> {
        let grown = self.division.root.grown(subspace.node, self.division.overlap);
        let mut parts: Vec<&dyn PointSource> = vec![file];
        parts.extend(bucket.map(|bucket| bucket as &dyn PointSource));
        let name = self.file_name(subspace.node);
        let path = self.dir.join(STAGING).join(&name);
        let points = concatenate(&path, &self.layout, &format!("updated {}", subspace.file), &parts)?;
        self.report.files_written += 1;
        self.report.points_written += points;
        Ok(Subspace {
            file: name,
            core: subspace.core,
            grown: Cube::of(&grown),
            points,
            core_points: subspace.core_points + new,
            node: subspace.node,
        })
    }

    /// The points of `copy` sorted in one pass into one binary PLY per cube of `grown` (of
    /// nodes at most `deepest` levels down) in the staging folder: bucket k holds, in the
    /// copy's order, every point in the k-th cube (a point in several cubes goes to each).
    /// Removed with the staging folder.
    fn buckets_of_new_points(
        &mut self,
        copy: &PointCloudFile,
        deepest: u32,
        grown: impl Iterator<Item = super::grid::Bounds>,
    ) -> Result<Vec<PointCloudFile>> {
        let grown: Vec<_> = grown.collect();
        let staging = self.dir.join(STAGING);
        let files: Vec<(std::path::PathBuf, String)> = (0..grown.len())
            .map(|k| (staging.join(format!("new-points-{k}.ply")), "new points".to_string()))
            .collect();
        let paths: Vec<_> = files.iter().map(|(path, _)| path.clone()).collect();
        let feeds = [Feed {
            source: copy as &dyn PointSource,
            keep: None,
        }];
        // A lookup as deep as the deepest owner lists about one cube a cell.
        self.write_targets(Node::ROOT, deepest.min(MAX_LOOKUP_DEPTH), &feeds, files, &grown)?;
        paths
            .iter()
            .map(|path| open_point_cloud(path).map_err(DivideError::PointCloud))
            .collect()
    }
}

/// The owners divided again: every empty one, and every subspace whose core would pass
/// `max_points` with its `new_core` points; or the root alone (everything divided afresh) when
/// those hold at least half of all points, old and new (`new_points`). Dividing the owners one
/// by one costs a counting pass each: where they are most of the points, one division from
/// the root costs less and rewrites hardly more (2,000,000 points added to as many in 43
/// subspaces, all divided again: 0.99 s one by one, 0.31 s afresh).
fn owners_to_divide_again(
    new_core: &BTreeMap<Owner, u64>,
    subspaces: &[Subspace],
    max_points: u64,
    new_points: u64,
) -> Vec<Owner> {
    let redo: Vec<Owner> = new_core
        .iter()
        .filter(|(owner, new)| match owner {
            Owner::Subspace(i) => subspaces.get(*i).is_some_and(|s| s.core_points + **new > max_points),
            Owner::Empty(_) => true,
        })
        .map(|(owner, _)| *owner)
        .collect();
    let everything = owner_points(&Owner::Empty(Node::ROOT), subspaces, new_core, new_points);
    let redo_points: u64 = redo
        .iter()
        .map(|owner| owner_points(owner, subspaces, new_core, new_points))
        .sum();
    if redo_points.saturating_mul(2) >= everything {
        vec![Owner::Empty(Node::ROOT)]
    } else {
        redo
    }
}

/// The points in `owner`'s core once its new ones are added: a subspace's old and new core
/// points; an empty node's new points; the root's, all points old and new (`new_points`).
fn owner_points(owner: &Owner, subspaces: &[Subspace], new_core: &BTreeMap<Owner, u64>, new_points: u64) -> u64 {
    match owner {
        Owner::Empty(node) if *node == Node::ROOT => subspaces.iter().map(|s| s.core_points).sum::<u64>() + new_points,
        Owner::Subspace(i) => {
            subspaces.get(*i).map_or(0, |s| s.core_points) + new_core.get(owner).copied().unwrap_or(0)
        }
        Owner::Empty(_) => new_core.get(owner).copied().unwrap_or(0),
    }
}

/// The points of `feeds`, in their order, copied into one binary PLY in `staging` (removed with
/// the staging folder when the divide ends).
fn copy_of_new_points(feeds: &[Feed<'_>], layout: &PointLayout, staging: &Path) -> Result<PointCloudFile> {
    let path = staging.join("new-points.ply");
    let sources: Vec<&dyn PointSource> = feeds.iter().map(|feed| feed.source).collect();
    concatenate(&path, layout, "new points", &sources)?;
    open_point_cloud(&path).map_err(DivideError::PointCloud)
}

/// Writes the points of `sources`, in their order, as one binary PLY of `layout` at `path`
/// (synced, as the write pass's files are); returns their number.
fn concatenate(path: &Path, layout: &PointLayout, note: &str, sources: &[&dyn PointSource]) -> Result<u64> {
    use std::io::{Seek, SeekFrom, Write};
    let file = std::fs::File::create(path).map_err(io("create", path))?;
    let mut out = std::io::BufWriter::with_capacity(BLOCK_BYTES, file);
    out.write_all(&fixed_header(layout, 0, note))
        .map_err(io("write", path))?;
    let block_points = (BLOCK_BYTES / layout.record_len().max(1)).max(1);
    let mut count = 0;
    for source in sources {
        count += source.for_each_block(block_points, &mut |block| {
            out.write_all(block).map_err(io("write", path))
        })?;
    }
    let mut file = out.into_inner().map_err(|e| io("write", path)(e.into_error()))?;
    // The header has one length whatever the count: write it again with the count.
    file.seek(SeekFrom::Start(0)).map_err(io("write", path))?;
    file.write_all(&fixed_header(layout, count, note))
        .map_err(io("write", path))?;
    file.sync_all().map_err(io("sync", path))?;
    Ok(count)
}

/// The new points must have the folder's properties; the limit and the overlap stay its own.
fn check_compatible(
    sources: &[&dyn PointSource],
    dir: &Path,
    division: &super::Division,
    layout: &PointLayout,
    options: &DivideOptions,
) -> Result<()> {
    if options.max_points != division.max_points || options.overlap != division.overlap {
        return Err(DivideError::LimitsDiffer {
            folder: dir.to_path_buf(),
            max_points: division.max_points,
            overlap: division.overlap,
            asked_max_points: options.max_points,
            asked_overlap: options.overlap,
        });
    }
    for source in sources {
        if source.layout() != layout {
            return Err(DivideError::PropertiesDiffer {
                input: source.describe(),
                properties: super::property_list(source.layout()),
                other: format!("the division in {}", dir.display()),
                other_properties: super::property_list(layout),
            });
        }
    }
    Ok(())
}

/// New points in each owner's core, and the subspaces whose grown cube receives new points.
fn owners_of_new_points(
    feeds: &[Feed<'_>],
    layout: &PointLayout,
    subspaces: &[Subspace],
    division: &super::Division,
    options: &DivideOptions,
) -> Result<(BTreeMap<Owner, u64>, BTreeSet<usize>)> {
    let root = division.root;
    // Every point asks these sets about each level down to its subspace: a fast hash.
    let leaves: HashMap<Node, usize, foldhash::fast::FixedState> =
        subspaces.iter().enumerate().map(|(i, s)| (s.node, i)).collect();
    let mut inner: std::collections::HashSet<Node, foldhash::fast::FixedState> = Default::default();
    for s in subspaces {
        for level in 0..s.node.level {
            inner.insert(s.node.ancestor(level));
        }
    }
    let deepest = subspaces.iter().map(|s| s.node.level).max().unwrap_or(0);
    let grown: Vec<_> = subspaces.iter().map(|s| root.grown(s.node, division.overlap)).collect();
    let lookup = Lookup::new(&root, Node::ROOT, deepest.min(MAX_LOOKUP_DEPTH), &grown);
    let owner_of = |g: [u32; 3]| {
        let mut level = 0;
        loop {
            let node = Node::holding(g, level);
            if let Some(&i) = leaves.get(&node) {
                return Owner::Subspace(i);
            }
            if !inner.contains(&node) || level == super::GRID_BITS {
                return Owner::Empty(node);
            }
            level += 1;
        }
    };
    let mut counts: BTreeMap<Owner, u64> = BTreeMap::new();
    let mut touched = BTreeSet::new();
    let bar = progress(options, "owners", feeds);
    stream(
        feeds,
        layout,
        &bar,
        |block, _| {
            // Runs of points with one owner counted as one entry: neighbouring points mostly
            // share their subspace.
            let mut owners: Vec<(Owner, u64)> = Vec::new();
            let mut hits: BTreeSet<u32> = BTreeSet::new();
            let mut last_hit = None;
            for record in block.chunks_exact(layout.record_len()) {
                let p = layout.position(record);
                let g = root.grid(p);
                let owner = owner_of(g);
                match owners.last_mut() {
                    Some((last, count)) if *last == owner => *count += 1,
                    _ => owners.push((owner, 1)),
                }
                lookup.place_grid(g, p, &grown, |t| {
                    if last_hit != Some(t) {
                        hits.insert(t);
                        last_hit = Some(t);
                    }
                });
            }
            (owners, hits)
        },
        |_, (owners, hits)| {
            for (owner, count) in owners {
                *counts.entry(owner).or_insert(0) += count;
            }
            touched.extend(hits.into_iter().map(|t| t as usize));
            Ok(())
        },
    )?;
    bar.finish_and_clear();
    Ok((counts, touched))
}
