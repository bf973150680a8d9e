//! (f) of issue 21: the deployment files parse, and every `mwb` command line they run — compose
//! `command:`, Kubernetes container `args:`, systemd `ExecStart=`, and the `mwb …` lines of
//! deploy/README.md — is accepted by the real command-line parser (`mwb::cli::command()`), so
//! a renamed subcommand or flag fails here instead of in an admin's cluster. Files the
//! kustomizations name must exist (except the certificates `mwb certs` writes).

use std::path::{Path, PathBuf};

fn deploy() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy")
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Every YAML document of a file, with `<<` merge keys applied.
fn yaml_documents(path: &Path) -> Vec<serde_yaml::Value> {
    let text = read(path);
    serde_yaml::Deserializer::from_str(&text)
        .map(|doc| {
            let mut v = <serde_yaml::Value as serde::Deserialize>::deserialize(doc)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            v.apply_merge()
                .unwrap_or_else(|e| panic!("{}: merge keys: {e}", path.display()));
            v
        })
        .collect()
}

fn strings(v: &serde_yaml::Value, what: &str) -> Vec<String> {
    v.as_sequence()
        .unwrap_or_else(|| panic!("{what}: not a list"))
        .iter()
        .map(|s| {
            s.as_str()
                .unwrap_or_else(|| panic!("{what}: {s:?} is not a string"))
                .to_owned()
        })
        .collect()
}

/// The real parser accepts `args` (after the program name), or the error names the place.
fn check_mwb(args: &[String], place: &str) {
    let argv = std::iter::once("mwb".to_owned()).chain(args.iter().cloned());
    if let Err(e) = mwb::cli::command().try_get_matches_from(argv) {
        panic!(
            "{place}: `mwb {}` is not a valid command line:\n{e}",
            args.join(" ")
        );
    }
}

#[test]
fn the_check_rejects_what_mwb_rejects() {
    for bad in [
        vec!["stor"],
        vec!["store", "--no-such-flag"],
        vec!["sampler", "--workers", "many"],
    ] {
        let argv = std::iter::once("mwb").chain(bad.iter().copied());
        assert!(
            mwb::cli::command().try_get_matches_from(argv).is_err(),
            "accepted {bad:?}"
        );
    }
}

/// The files deploy/Dockerfile copies into /etc/mwb/ (from `COPY deploy/… /etc/mwb/` lines).
fn dockerfile_configs() -> Vec<String> {
    let text = read(&deploy().join("Dockerfile"));
    let configs: Vec<String> = text
        .lines()
        .filter_map(|l| l.strip_prefix("COPY "))
        .filter(|l| l.trim_end().ends_with(" /etc/mwb/"))
        .flat_map(|l| {
            l.split_whitespace()
                .filter_map(|w| w.strip_prefix("deploy/"))
        })
        .map(str::to_owned)
        .collect();
    assert!(!configs.is_empty(), "deploy/Dockerfile copies no config");
    for c in &configs {
        assert!(
            deploy().join(c).is_file(),
            "deploy/Dockerfile copies missing deploy/{c}"
        );
    }
    configs
}

#[test]
fn compose_runs_only_what_mwb_has() {
    let path = deploy().join("compose.yaml");
    let docs = yaml_documents(&path);
    let services = docs[0]["services"]
        .as_mapping()
        .unwrap_or_else(|| panic!("{}: no services", path.display()));
    assert!(services.len() >= 3, "store, sampler, reverse expected");
    let image_configs = dockerfile_configs();
    for (name, svc) in services {
        let name = name.as_str().unwrap_or("?");
        let place = format!("{} services.{name}", path.display());
        let command = strings(&svc["command"], &place);
        check_mwb(&command, &place);
        assert_eq!(
            svc["image"].as_str(),
            Some("manyworlds/mwb:latest"),
            "{place}: image"
        );
        // Every config a command names is in the image.
        for config in command.iter().filter_map(|a| a.strip_prefix("/etc/mwb/")) {
            assert!(
                image_configs.iter().any(|c| c == config),
                "{place}: /etc/mwb/{config} is not copied by deploy/Dockerfile ({image_configs:?})"
            );
        }
        // Each service mounts a bundle of `mwb certs` where the shipped configs look.
        let volumes = strings(&svc["volumes"], &place);
        assert!(
            volumes.iter().any(|v| v.ends_with(":/etc/mwb/tls:ro")),
            "{place}: no certificate bundle on /etc/mwb/tls"
        );
    }
}

#[test]
fn kubernetes_runs_only_what_mwb_has() {
    let dir = deploy().join("k8s");
    let mut containers = 0;
    for entry in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.unwrap_or_else(|e| panic!("{e}")).path();
        if path.extension().and_then(|e| e.to_str()) != Some("yaml") {
            continue;
        }
        for (i, doc) in yaml_documents(&path).iter().enumerate() {
            assert!(
                doc["kind"].is_string(),
                "{} document {i}: no kind",
                path.display()
            );
            let spec = &doc["spec"]["template"]["spec"]["containers"];
            if spec.is_null() {
                continue;
            }
            for c in spec.as_sequence().into_iter().flatten() {
                let place = format!("{} document {i} container {:?}", path.display(), c["name"]);
                assert!(
                    c["command"].is_null(),
                    "{place}: the image's entrypoint is mwb"
                );
                check_mwb(&strings(&c["args"], &place), &place);
                containers += 1;
            }
        }
    }
    assert!(containers >= 2, "store and sampler containers expected");
}

#[test]
fn kustomizations_name_files_that_exist() {
    for path in [
        deploy().join("kustomization.yaml"),
        deploy().join("k8s/kustomization.yaml"),
    ] {
        let base = path
            .parent()
            .unwrap_or_else(|| panic!("{}", path.display()));
        let doc = &yaml_documents(&path)[0];
        let mut named: Vec<String> = Vec::new();
        if !doc["resources"].is_null() {
            named.extend(strings(&doc["resources"], "resources"));
        }
        for generator in ["configMapGenerator", "secretGenerator"] {
            for g in doc[generator].as_sequence().into_iter().flatten() {
                for f in strings(&g["files"], generator) {
                    // `key=path` or `path`
                    let file = f.split_once('=').map_or(f.as_str(), |(_, p)| p);
                    named.push(file.to_owned());
                }
            }
        }
        assert!(!named.is_empty(), "{}: names nothing", path.display());
        for f in named {
            if f.starts_with("certs/") {
                continue; // written by `mwb certs` before `kubectl apply -k`
            }
            assert!(
                base.join(&f).exists(),
                "{}: names {f}, which does not exist",
                path.display()
            );
        }
    }
}

#[test]
fn systemd_units_run_only_what_mwb_has() {
    let dir = deploy().join("systemd");
    let mut units = 0;
    for entry in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.unwrap_or_else(|e| panic!("{e}")).path();
        for line in read(&path).lines() {
            if let Some(cmd) = line.strip_prefix("ExecStart=") {
                let words: Vec<String> = cmd.split_whitespace().map(str::to_owned).collect();
                assert_eq!(
                    words.first().map(String::as_str),
                    Some("/usr/local/bin/mwb")
                );
                check_mwb(&words[1..], &path.display().to_string());
                units += 1;
            }
        }
    }
    assert!(units >= 2, "store and sampler units expected");
}

/// The walkthrough's `mwb …` lines (in fenced blocks; `\` continuations joined, `#` comments
/// dropped) are valid command lines.
#[test]
fn readme_walkthrough_runs_only_what_mwb_has() {
    let path = deploy().join("README.md");
    let text = read(&path);
    let mut in_block = false;
    let mut pending = String::new();
    let mut checked = 0;
    for (n, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("```") {
            in_block = !in_block;
            continue;
        }
        if !in_block {
            continue;
        }
        let line = line.split(" #").next().unwrap_or("").trim();
        if pending.is_empty() && !line.starts_with("mwb ") {
            continue;
        }
        if let Some(head) = line.strip_suffix('\\') {
            pending.push_str(head);
            pending.push(' ');
            continue;
        }
        pending.push_str(line);
        let words: Vec<String> = pending
            .split_whitespace()
            .skip(1)
            .map(str::to_owned)
            .collect();
        check_mwb(&words, &format!("{}:{}", path.display(), n + 1));
        pending.clear();
        checked += 1;
    }
    assert!(checked >= 5, "{}: only {checked} mwb lines", path.display());
}
