//! Saved views kept with the session: one small JSON file per session name, so the cameras an
//! animator keeps (the Views panel) are there again when the viewer is reopened on the same
//! session (issue: viewer, "camera bookmarks kept with the session").
//!
//! The file lives under the user's configuration directory —
//! `$XDG_CONFIG_HOME/manyworlds/views/<session>.json` (else `~/.config/manyworlds/views/…`; on
//! Windows `%APPDATA%\manyworlds\views\…`) — unless `mwb viewer --views-file` (or
//! [`VIEWS_FILE_ENV`]) names another. [`crate::ViewerState`] only holds the views; the app
//! ([`crate::ViewerApp::with_views_file`]) reads them at start and writes them whenever
//! [`crate::ViewerState::views_edits`] moves. Writes go to a temporary file in the same
//! directory that is then renamed over the old one, so a crash never leaves half a file. A file
//! that cannot be read is reported (the status bar shows it), never fatal; it is kept beside
//! the new one as `<name>.json.bad` when a view is next saved.
//!
//! ```
//! use mwb_viewer::views::{decode, encode};
//! use mwb_viewer::{OrbitCamera, state::SavedView};
//!
//! let views = vec![SavedView { name: "top".into(), camera: OrbitCamera::default() }];
//! let text = encode("viewer", &views);
//! assert!(text.contains("\"version\": 1"));
//! assert_eq!(decode(&text, "views.json").unwrap(), views);
//! assert!(decode("{ \"version\": 1, ", "views.json").is_err());
//! ```

use std::ffi::OsString;
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::camera::{MAX_PITCH_RAD, MIN_DISTANCE_M};
use crate::state::SavedView;

/// Environment variable naming the views file (what `mwb viewer --views-file` defaults to):
/// tests set it so that they never touch the user's home directory.
pub const VIEWS_FILE_ENV: &str = "MWB_VIEWS_FILE";
/// The file format's version; a file of another version is refused, not guessed at.
pub const FORMAT_VERSION: u32 = 1;

/// What can go wrong with a views file. Each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ViewsError {
    #[error("views file {path}: {source}")]
    Read {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("views file {path}:{line}:{column}: {source}")]
    Parse {
        path: String,
        line: usize,
        column: usize,
        #[source]
        source: serde_json::Error,
    },
    #[error("views file {path}: version {found}, this viewer reads version {expected}")]
    Version {
        path: String,
        found: u32,
        expected: u32,
    },
    #[error("views file {path}: view {index} ({name:?}): {what}")]
    Invalid {
        path: String,
        index: usize,
        name: String,
        what: String,
    },
    #[error("writing views file {path}: {source}")]
    Write {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

/// The file as written: its version, the session it belongs to (for a reader's benefit only;
/// the file name is what is looked up) and the views in the order saved.
#[derive(Debug, Serialize, Deserialize)]
struct FileContents {
    version: u32,
    #[serde(default)]
    session: String,
    views: Vec<SavedView>,
}

/// The JSON text of a session's views.
pub fn encode(session: &str, views: &[SavedView]) -> String {
    let contents = FileContents {
        version: FORMAT_VERSION,
        session: session.to_owned(),
        views: views.to_vec(),
    };
    // A struct of strings and finite-or-not floats always serialises (serde_json writes a
    // non-finite float as null, which `decode` then refuses by name).
    let mut text = serde_json::to_string_pretty(&contents).unwrap_or_default();
    text.push('\n');
    text
}

/// The views in a file's text; `path` names the file in errors. Every camera must be usable:
/// finite numbers, a positive distance and field of view, 0 < near < far.
pub fn decode(text: &str, path: &str) -> Result<Vec<SavedView>, ViewsError> {
    let contents: FileContents = serde_json::from_str(text).map_err(|e| ViewsError::Parse {
        path: path.to_owned(),
        line: e.line(),
        column: e.column(),
        source: e,
    })?;
    if contents.version != FORMAT_VERSION {
        return Err(ViewsError::Version {
            path: path.to_owned(),
            found: contents.version,
            expected: FORMAT_VERSION,
        });
    }
    for (index, v) in contents.views.iter().enumerate() {
        if let Err(what) = check_camera(v) {
            return Err(ViewsError::Invalid {
                path: path.to_owned(),
                index,
                name: v.name.clone(),
                what,
            });
        }
    }
    Ok(contents.views)
}

/// Why a saved camera cannot be used, naming the field.
fn check_camera(v: &SavedView) -> Result<(), String> {
    let c = &v.camera;
    let numbers = [
        ("target", c.target[0]),
        ("target", c.target[1]),
        ("target", c.target[2]),
        ("yaw", c.yaw),
        ("pitch", c.pitch),
        ("distance", c.distance),
        ("fov_y_rad", c.fov_y_rad),
        ("near", c.near),
        ("far", c.far),
    ];
    if let Some((field, value)) = numbers.iter().find(|(_, x)| !x.is_finite()) {
        return Err(format!("{field} {value} is not a finite number"));
    }
    if c.pitch.abs() > MAX_PITCH_RAD {
        return Err(format!("pitch {} is beyond ±{MAX_PITCH_RAD} rad", c.pitch));
    }
    if c.distance < MIN_DISTANCE_M {
        return Err(format!(
            "distance {} is below {MIN_DISTANCE_M} m",
            c.distance
        ));
    }
    if !(c.fov_y_rad > 0.0 && c.fov_y_rad < std::f64::consts::PI) {
        return Err(format!("fov_y_rad {} is not in (0, π)", c.fov_y_rad));
    }
    if !(c.near > 0.0 && c.far > c.near) {
        return Err(format!(
            "near {} and far {} are not 0 < near < far",
            c.near, c.far
        ));
    }
    Ok(())
}

/// The platform conventions for the configuration directory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Platform {
    /// `$XDG_CONFIG_HOME`, else `$HOME/.config` (Linux, BSD, macOS).
    Unix,
    /// `%APPDATA%`.
    Windows,
}

impl Platform {
    pub fn current() -> Self {
        if cfg!(windows) {
            Platform::Windows
        } else {
            Platform::Unix
        }
    }
}

/// The directory the views files live in, from the environment `var` (`None`: no home or
/// configuration directory is known).
pub fn views_dir_from(
    platform: Platform,
    var: impl Fn(&str) -> Option<OsString>,
) -> Option<PathBuf> {
    // Relative or empty values are ignored, as the XDG base directory specification says.
    let absolute = |name: &str| var(name).map(PathBuf::from).filter(|p| p.is_absolute());
    let config = match platform {
        Platform::Windows => absolute("APPDATA")?,
        Platform::Unix => {
            absolute("XDG_CONFIG_HOME").or_else(|| absolute("HOME").map(|h| h.join(".config")))?
        }
    };
    Some(config.join("manyworlds").join("views"))
}

/// The file name of a session's views: the session name with anything but ASCII letters,
/// digits, `-`, `_` and `.` replaced by `_` (and no leading dot), plus `.json`.
pub fn file_name(session: &str) -> String {
    let mut name: String = session
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.') {
                c
            } else {
                '_'
            }
        })
        .collect();
    if name.is_empty() || name.starts_with('.') {
        name.insert(0, '_');
    }
    name + ".json"
}

/// Where a session's views are kept by default on this machine (`None`: no configuration
/// directory is known; then the views last only as long as the viewer runs).
pub fn default_path(session: &str) -> Option<PathBuf> {
    views_dir_from(Platform::current(), |name| std::env::var_os(name))
        .map(|dir| dir.join(file_name(session)))
}

/// One session's views file: read once at start, rewritten (atomically) on every change.
#[derive(Debug, Clone)]
pub struct ViewsFile {
    path: PathBuf,
    session: String,
    /// The file on disk could not be read: move it aside (not over it) at the next write.
    keep_bad: bool,
}

impl ViewsFile {
    pub fn new(path: impl Into<PathBuf>, session: impl Into<String>) -> Self {
        Self {
            path: path.into(),
            session: session.into(),
            keep_bad: false,
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The views kept in the file; none if there is no file yet.
    pub fn load(&mut self) -> Result<Vec<SavedView>, ViewsError> {
        let shown = self.path.display().to_string();
        let text = match std::fs::read_to_string(&self.path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(source) => {
                return Err(ViewsError::Read {
                    path: shown,
                    source,
                });
            }
        };
        let views = decode(&text, &shown);
        self.keep_bad = views.is_err();
        views
    }

    /// Replaces the file with `views`: written to a temporary file beside it, flushed, then
    /// renamed over it (the directory is made if need be). A file that could not be read is
    /// first moved aside to `<name>.bad`.
    pub fn save(&mut self, views: &[SavedView]) -> Result<(), ViewsError> {
        let fail = |source| ViewsError::Write {
            path: self.path.display().to_string(),
            source,
        };
        if let Some(dir) = self.path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(fail)?;
        }
        if self.keep_bad {
            let mut bad = self.path.clone().into_os_string();
            bad.push(".bad");
            match std::fs::rename(&self.path, &bad) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(fail(e)),
            }
            self.keep_bad = false;
        }
        let mut tmp = self.path.clone().into_os_string();
        tmp.push(format!(".tmp{}", std::process::id()));
        let tmp = PathBuf::from(tmp);
        let written = std::fs::File::create(&tmp).and_then(|mut f| {
            f.write_all(encode(&self.session, views).as_bytes())?;
            f.sync_all()
        });
        if let Err(e) = written.and_then(|()| std::fs::rename(&tmp, &self.path)) {
            // The temporary file is ours alone; a failed removal leaves only a stray file.
            std::fs::remove_file(&tmp).ok();
            return Err(fail(e));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::OrbitCamera;

    fn views() -> Vec<SavedView> {
        vec![
            SavedView {
                name: "front".into(),
                camera: OrbitCamera::default(),
            },
            SavedView {
                name: "över the tower".into(),
                camera: OrbitCamera {
                    target: [1.25, -0.5, 3.0],
                    yaw: 5.9,
                    pitch: -1.2,
                    distance: 0.3,
                    fov_y_rad: 0.7,
                    near: 0.01,
                    far: 5000.0,
                },
            },
        ]
    }

    /// A fresh directory under the system's temporary directory (never the home directory).
    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("mwb-viewer-views-{}-{name}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        dir
    }

    #[test]
    fn views_round_trip_through_the_file_bit_for_bit() {
        let dir = scratch("round-trip");
        let path = dir.join("nested").join("viewer.json");
        let mut file = ViewsFile::new(&path, "viewer");
        assert_eq!(file.load().expect("no file yet"), Vec::new());
        file.save(&views()).expect("writes, making the directories");
        let mut again = ViewsFile::new(&path, "viewer");
        assert_eq!(again.load().expect("reads"), views());
        // Rewritten in place; nothing else is left in the directory.
        again.save(&views()[..1]).expect("rewrites");
        assert_eq!(again.load().expect("reads"), views()[..1].to_vec());
        let left: Vec<_> = std::fs::read_dir(dir.join("nested"))
            .expect("dir")
            .filter_map(Result::ok)
            .map(|e| e.file_name())
            .collect();
        assert_eq!(left, vec![OsString::from("viewer.json")]);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_corrupt_file_is_an_error_naming_it_and_is_kept_aside_at_the_next_save() {
        let dir = scratch("corrupt");
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("viewer.json");
        std::fs::write(&path, "{\"version\": 1, \"views\": [{\"name\": \"a\",").expect("write");
        let mut file = ViewsFile::new(&path, "viewer");
        let e = file.load().expect_err("truncated JSON").to_string();
        assert!(
            e.starts_with(&format!("views file {}:1:", path.display())),
            "{e}"
        );
        file.save(&views()).expect("writes");
        assert_eq!(
            std::fs::read_to_string(dir.join("viewer.json.bad")).expect("kept"),
            "{\"version\": 1, \"views\": [{\"name\": \"a\","
        );
        assert_eq!(file.load().expect("the new file reads"), views());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn unusable_contents_are_refused_by_name() {
        let good = encode("s", &views());
        let cases = [
            (
                good.replace("\"version\": 1", "\"version\": 7"),
                "version 7",
            ),
            (
                good.replace("\"distance\": 0.3", "\"distance\": -2.0"),
                "view 1 (\"över the tower\"): distance -2",
            ),
            (
                good.replace("\"fov_y_rad\": 0.7", "\"fov_y_rad\": null"),
                "views file f.json:",
            ),
            (
                good.replace("\"far\": 5000.0", "\"far\": 0.001"),
                "near 0.01 and far 0.001",
            ),
            ("[]".to_owned(), "views file f.json:1:"),
            (String::new(), "views file f.json:1:"),
        ];
        for (text, want) in cases {
            let e = decode(&text, "f.json").expect_err(want).to_string();
            assert!(e.contains(want), "{e:?} should say {want:?}");
        }
    }

    #[test]
    fn the_default_place_follows_the_platform_and_names_are_made_safe() {
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |name: &str| {
                pairs
                    .iter()
                    .find(|(k, _)| *k == name)
                    .map(|(_, v)| OsString::from(v))
            }
        };
        assert_eq!(
            views_dir_from(
                Platform::Unix,
                env(&[("XDG_CONFIG_HOME", "/x/cfg"), ("HOME", "/home/a")])
            ),
            Some(PathBuf::from("/x/cfg/manyworlds/views"))
        );
        // A relative XDG_CONFIG_HOME is ignored.
        assert_eq!(
            views_dir_from(
                Platform::Unix,
                env(&[("XDG_CONFIG_HOME", "cfg"), ("HOME", "/home/a")])
            ),
            Some(PathBuf::from("/home/a/.config/manyworlds/views"))
        );
        assert_eq!(views_dir_from(Platform::Unix, env(&[])), None);
        if cfg!(windows) {
            assert_eq!(
                views_dir_from(
                    Platform::Windows,
                    env(&[("APPDATA", r"C:\Users\a\AppData\Roaming")])
                ),
                Some(PathBuf::from(
                    r"C:\Users\a\AppData\Roaming\manyworlds\views"
                ))
            );
        } else {
            // "C:\…" is not an absolute path here; any absolute one shows the layout.
            assert_eq!(
                views_dir_from(Platform::Windows, env(&[("APPDATA", "/appdata")])),
                Some(PathBuf::from("/appdata/manyworlds/views"))
            );
        }
        assert_eq!(
            views_dir_from(Platform::Windows, env(&[("HOME", "/home/a")])),
            None
        );
        assert_eq!(file_name("viewer"), "viewer.json");
        assert_eq!(file_name("../etc/passwd"), "_.._etc_passwd.json");
        assert_eq!(file_name(".hidden"), "_.hidden.json");
        assert_eq!(file_name(""), "_.json");
        assert_eq!(file_name("offline-tumble"), "offline-tumble.json");
    }
}
