//! Writing meshes: binary little-endian PLY (with normals) or OBJ.

use std::io::Write;
use std::path::Path;

use super::Mesh;

/// The header of the binary PLY that octstore writes: float positions and normals, then
/// triangles as uchar-counted uint lists.
pub fn ply_header(vertices: u64, triangles: u64) -> String {
    format!(
        "ply\nformat binary_little_endian 1.0\ncomment octstore\nelement vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face {triangles}\nproperty list uchar uint vertex_indices\nend_header\n"
    )
}

/// The temporary name beside `path` that a writer of `path` uses for `part`: hidden, and
/// ending in `.tmp`, so that [`remove_leftovers`] finds it after a killed run.
pub fn temporary_beside(path: &Path, part: &str) -> std::path::PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.{part}.tmp"))
}

/// Removes what a killed writer of `path` left beside it ([`temporary_beside`] names). One
/// writer per output path at a time: a second one's parts would be removed too.
pub fn remove_leftovers(path: &Path) -> std::io::Result<()> {
    let Some(name) = path.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return Ok(());
    };
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    let prefix = format!(".{name}.");
    let entries = match std::fs::read_dir(&dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(e),
    };
    for entry in entries {
        let entry = entry?;
        let file = entry.file_name().to_string_lossy().into_owned();
        if file.starts_with(&prefix) && file.ends_with(".tmp") {
            std::fs::remove_file(entry.path())?;
        }
    }
    Ok(())
}

/// Where a write of `path` goes: `path` itself, or the file a symbolic link at `path` leads to,
/// so that the link stays a link and its target is what is replaced. A path that exists and is
/// not a regular file (a folder, a FIFO, a device) is refused: the atomic rename would replace
/// it with a regular file.
pub fn output_target(path: &Path) -> std::io::Result<std::path::PathBuf> {
    /// Links followed before giving up, as the kernel's `ELOOP` limit.
    const MAX_LINKS: usize = 40;
    let mut target = path.to_path_buf();
    for _ in 0..MAX_LINKS {
        match std::fs::symlink_metadata(&target) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(target),
            Err(e) => return Err(e),
            Ok(meta) if meta.file_type().is_symlink() => {
                let link = std::fs::read_link(&target)?;
                // `join` keeps an absolute link as it is and resolves a relative one from the
                // link's folder.
                target = match target.parent() {
                    Some(dir) => dir.join(link),
                    None => link,
                };
            }
            Ok(meta) if meta.is_file() => return Ok(target),
            Ok(_) => {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    format!(
                        "{} is not a regular file (a folder, FIFO or device): outputs are written to a new or regular file only",
                        target.display()
                    ),
                ));
            }
        }
    }
    Err(std::io::Error::new(
        std::io::ErrorKind::InvalidInput,
        format!("{}: more than {MAX_LINKS} symbolic links in a row", path.display()),
    ))
}

/// Writes `path` atomically: `write` fills a temporary file beside it, which is flushed,
/// synced and renamed over `path`, so a reader (or a killed run) sees the old file or the whole
/// new one, never a part. On an error the temporary file is removed and `path` is untouched.
/// A symbolic link at `path` stays, and its target is replaced ([`output_target`]).
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let path = &output_target(path)?;
    let temporary = temporary_beside(path, &format!("{}.out", std::process::id()));
    let result = (|| {
        let mut out = std::io::BufWriter::new(std::fs::File::create(&temporary)?);
        write(&mut out)?;
        out.into_inner().map_err(|e| e.into_error())?.sync_all()?;
        std::fs::rename(&temporary, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&temporary);
    }
    result
}

/// Writes binary little-endian PLY, or OBJ when the path ends in `.obj`, atomically
/// ([`write_atomically`]). A mesh without normals gets zero normals in PLY (whose header always
/// has them) and none in OBJ.
pub fn write_mesh(path: &Path, mesh: &Mesh) -> std::io::Result<()> {
    let path = &output_target(path)?;
    remove_leftovers(path)?;
    write_atomically(path, |out| write_mesh_to(path, mesh, out))
}

fn write_mesh_to(path: &Path, mesh: &Mesh, out: &mut impl Write) -> std::io::Result<()> {
    let is_obj = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("obj"));
    let has_normals = mesh.normals.len() == mesh.positions.len();
    let normal = |i: usize| {
        if has_normals {
            mesh.normals.get(i).copied().unwrap_or_default()
        } else {
            [0.0; 3]
        }
    };
    if super::glb::is_glb(path) {
        let (min, max) = super::glb::bounds(mesh.positions.iter());
        let (vertices, triangles) = (mesh.positions.len() as u64, mesh.triangles.len() as u64);
        super::glb::write_glb_head(out, vertices, triangles, min, max)?;
        for (i, p) in mesh.positions.iter().enumerate() {
            for v in p.iter().chain(&normal(i)) {
                out.write_all(&v.to_le_bytes())?;
            }
        }
        for t in &mesh.triangles {
            for v in t {
                out.write_all(&v.to_le_bytes())?;
            }
        }
    } else if is_obj {
        for (i, p) in mesh.positions.iter().enumerate() {
            writeln!(out, "v {} {} {}", p[0], p[1], p[2])?;
            if has_normals {
                let n = normal(i);
                writeln!(out, "vn {} {} {}", n[0], n[1], n[2])?;
            }
        }
        for t in &mesh.triangles {
            if has_normals {
                writeln!(out, "f {0}//{0} {1}//{1} {2}//{2}", t[0] + 1, t[1] + 1, t[2] + 1)?;
            } else {
                writeln!(out, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
            }
        }
    } else {
        write!(
            out,
            "{}",
            ply_header(mesh.positions.len() as u64, mesh.triangles.len() as u64)
        )?;
        for (i, p) in mesh.positions.iter().enumerate() {
            for v in p.iter().chain(&normal(i)) {
                out.write_all(&v.to_le_bytes())?;
            }
        }
        for t in &mesh.triangles {
            out.write_all(&[3u8])?;
            for v in t {
                out.write_all(&v.to_le_bytes())?;
            }
        }
    }
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A symbolic link stays a link and its target gets the new bytes; a FIFO and a folder are
    /// refused and stay what they were.
    #[test]
    fn outputs_go_through_links_and_never_replace_what_is_not_a_file() {
        use std::os::unix::fs::FileTypeExt;
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("real.ply");
        std::fs::write(&target, b"old").unwrap();
        let link = dir.path().join("link.ply");
        std::os::unix::fs::symlink("real.ply", &link).unwrap();
        write_atomically(&link, |out| out.write_all(b"new")).unwrap();
        assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
        assert_eq!(std::fs::read(&target).unwrap(), b"new");
        // A dangling link creates its target.
        let dangling = dir.path().join("dangling.ply");
        std::os::unix::fs::symlink(dir.path().join("later.ply"), &dangling).unwrap();
        write_atomically(&dangling, |out| out.write_all(b"made")).unwrap();
        assert_eq!(std::fs::read(dir.path().join("later.ply")).unwrap(), b"made");

        let fifo = dir.path().join("fifo.ply");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status().unwrap();
        assert!(made.success());
        let folder = dir.path().join("folder.ply");
        std::fs::create_dir(&folder).unwrap();
        for refused in [&fifo, &folder] {
            let error = write_atomically(refused, |out| out.write_all(b"x")).unwrap_err();
            assert!(error.to_string().contains("not a regular file"), "{error}");
        }
        assert!(std::fs::symlink_metadata(&fifo).unwrap().file_type().is_fifo());
        assert!(std::fs::symlink_metadata(&folder).unwrap().is_dir());
        let leftovers: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".tmp"))
            .collect();
        assert!(leftovers.is_empty(), "{leftovers:?}");
    }

    /// A writer that fails half-way leaves the old file whole and nothing beside it; one that
    /// succeeds replaces it whole.
    #[test]
    fn atomic_writes_replace_the_old_file_whole_or_not_at_all() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mesh.ply");
        std::fs::write(&path, b"old mesh").unwrap();
        let failed = write_atomically(&path, |out| {
            out.write_all(b"half a new m")?;
            out.flush()?;
            Err(std::io::Error::other("disk full"))
        });
        assert!(failed.is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"old mesh");
        let names = |dir: &Path| {
            let mut names: Vec<String> = std::fs::read_dir(dir)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            names.sort();
            names
        };
        assert_eq!(names(dir.path()), ["mesh.ply"]);
        write_atomically(&path, |out| out.write_all(b"new mesh")).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new mesh");
        assert_eq!(names(dir.path()), ["mesh.ply"]);
    }

    /// What a killed writer of a path leaves beside it is removed, and nothing else.
    #[test]
    fn leftovers_of_a_killed_writer_are_removed_and_nothing_else() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mesh.ply");
        for name in [
            "mesh.ply",
            ".mesh.ply.vertices.tmp",
            ".mesh.ply.4242.out.tmp",
            ".other.ply.faces.tmp",
            "mesh.ply.tmp",
        ] {
            std::fs::write(dir.path().join(name), b"x").unwrap();
        }
        assert_eq!(temporary_beside(&path, "faces"), dir.path().join(".mesh.ply.faces.tmp"));
        remove_leftovers(&path).unwrap();
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, [".other.ply.faces.tmp", "mesh.ply", "mesh.ply.tmp"]);
        remove_leftovers(&dir.path().join("missing").join("mesh.ply")).unwrap();
    }
}
