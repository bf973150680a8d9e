//! Jobs as clients make them — the command line, the viewer's jobs panel, benchmarks: a scene
//! argument read (a file, or a shipped scene's name) and a sampling job built from it.

use mwb_core::scene::SceneTemplate;
use mwb_proto::v1::{Encoding, Job, JobKind, Quality, Scene};

/// Why a scene argument or a job could not be made. Names the file or the field.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("reading scene {path}")]
    Read {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("scene {arg:?}: no such file, and not a shipped scene ({known})")]
    UnknownScene { arg: String, known: String },
    #[error(transparent)]
    Scene(#[from] mwb_core::scene::SceneError),
    #[error(transparent)]
    Id(#[from] mwb_core::keys::BadIdentifier),
}

/// Reads a scene argument: a path to a TOML file, or the name of a shipped scene. Returns the
/// file name to report and the scene text, **self-contained**: the meshes a file names
/// (`shape = "mesh"`) are read, checked and decomposed here ([`mwb_mesh::resolve`], cached
/// beside each mesh) and written into the text, so a job made from it needs no files on the
/// machine that samples it. Shipped scenes have no meshes.
pub fn load_scene(arg: &str) -> Result<(String, String), JobError> {
    let path = std::path::Path::new(arg);
    if path.exists() {
        let bytes = std::fs::read(path).map_err(|source| JobError::Read {
            path: path.display().to_string(),
            source,
        })?;
        let text = mwb_core::scene::decode_utf8(arg, bytes)?;
        let dir = path.parent().unwrap_or(std::path::Path::new("."));
        let resolved = mwb_mesh::resolve(arg, &text, dir)?;
        return Ok((arg.to_owned(), resolved.text));
    }
    let name = arg.trim_end_matches(".toml");
    let name = name.rsplit('/').next().unwrap_or(name);
    match mwb_core::scene::builtin::get(name) {
        Some(text) => Ok((format!("scenes/{name}.toml"), text.to_owned())),
        None => Err(JobError::UnknownScene {
            arg: arg.to_owned(),
            known: mwb_core::scene::builtin::NAMES.join(", "),
        }),
    }
}

/// A sampling job for `target` worlds of the scene text (validated first), at the standard
/// codec quality. Without `id`, the id is the scene's name and the creation time in hex.
pub fn sample_job(
    file: &str,
    text: &str,
    target: u32,
    priority: i32,
    id: Option<String>,
    created_unix_ms: u64,
) -> Result<Job, JobError> {
    let template = SceneTemplate::parse(text, file)?;
    let id = match id {
        Some(id) => id,
        None => {
            let base: String = template
                .name()
                .chars()
                .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
                .take(40)
                .collect();
            format!(
                "{}-{created_unix_ms:x}",
                if base.is_empty() { "job" } else { &base }
            )
        }
    };
    mwb_core::keys::check_identifier("job id", &id)?;
    Ok(Job {
        id,
        revision: 1,
        kind: JobKind::Sample as i32,
        scene: Some(Scene {
            revision: 0,
            name: template.name().to_owned(),
            toml: text.to_owned(),
            content_hash: mwb_core::content_hash(text),
        }),
        target_worlds: target,
        priority,
        created_unix_ms,
        cancelled: false,
        encoding: Encoding::SplineV1 as i32,
        quality: Quality::Standard as i32,
        refine: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_scenes_by_name_and_jobs_named_after_them() {
        let (file, text) = load_scene("tumble").expect("ships");
        assert_eq!(file, "scenes/tumble.toml");
        let (same, _) = load_scene("scenes/tumble.toml")
            .or_else(|_| load_scene("tumble.toml"))
            .expect("the file name of a shipped scene works too");
        assert!(same.ends_with("tumble.toml"));
        let job = sample_job(&file, &text, 10, 0, None, 0xabc).expect("job");
        assert_eq!(job.id, "tumble-abc");
        assert_eq!(job.target_worlds, 10);
        assert_eq!(
            job.scene.as_ref().map(|s| s.content_hash),
            Some(mwb_core::content_hash(&text))
        );
    }

    #[test]
    fn a_scene_file_with_meshes_loads_self_contained() {
        // A copy of scenes/letters.toml and its props in a fresh directory: the decomposition
        // cache is written beside the copies, not into the repository.
        let repo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let dir = std::env::temp_dir().join(format!("mwb-node-letters-{}", std::process::id()));
        let copy = |from: &str| {
            let to = dir.join(from);
            std::fs::create_dir_all(to.parent().expect("has a parent")).expect("temp dir");
            std::fs::copy(repo.join("scenes").join(from), &to).expect("shipped file");
        };
        for f in [
            "letters.toml",
            "props/letter_m.obj",
            "props/letter_w.obj",
            "props/letter_b.obj",
        ] {
            copy(f);
        }
        let arg = dir.join("letters.toml").display().to_string();
        let (file, text) = load_scene(&arg).expect("resolves");
        std::fs::remove_dir_all(&dir).ok();
        assert_eq!(file, arg);
        assert!(!text.contains("shape = \"mesh\""), "{text}");
        let job = sample_job(&file, &text, 1, 0, None, 0).expect("a job of the resolved text");
        assert_eq!(job.scene.map(|s| s.toml), Some(text));
    }

    #[test]
    fn bad_arguments_are_named() {
        let e = load_scene("no-such-scene")
            .expect_err("unknown")
            .to_string();
        assert!(e.contains("no-such-scene") && e.contains("tumble"), "{e}");
        let (file, text) = load_scene("tumble").expect("ships");
        let e = sample_job(&file, &text, 1, 0, Some("a/b".into()), 0)
            .expect_err("bad id")
            .to_string();
        assert!(e.contains("a/b"), "{e}");
        assert!(sample_job("x.toml", "not = [toml", 1, 0, None, 0).is_err());
    }
}
