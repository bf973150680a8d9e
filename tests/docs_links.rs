//! Every relative link in the repository's documents (README.md, ARCHITECTURE.md, CHANGELOG.md
//! and docs/*.md) reaches a file of the repository — and, for `file.md#anchor`, a heading of
//! that file — so the documents work in any clone. Nothing may point at `../shared`, which
//! exists only in the authors' workspace. Pure file reading.

use std::collections::HashSet;
use std::path::{Component, Path, PathBuf};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The documents checked: the top-level guides and everything in docs/.
fn documents() -> Vec<PathBuf> {
    let root = Path::new(ROOT);
    let mut files: Vec<PathBuf> = ["README.md", "ARCHITECTURE.md", "CHANGELOG.md"]
        .iter()
        .map(|f| root.join(f))
        .filter(|p| p.exists())
        .collect();
    let docs = std::fs::read_dir(root.join("docs")).expect("reading docs/");
    for entry in docs {
        let path = entry.expect("reading docs/").path();
        if path.extension().is_some_and(|e| e == "md") {
            files.push(path);
        }
    }
    files.sort();
    files
}

/// The text outside fenced code blocks and code spans, line by line (links in code are not
/// links).
fn prose_lines(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut fenced = false;
    for (i, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        // Drop code spans: every other backtick-delimited piece.
        let prose: String = line
            .split('`')
            .enumerate()
            .filter(|(k, _)| k % 2 == 0)
            .map(|(_, s)| s)
            .collect::<Vec<_>>()
            .join(" ");
        out.push((i + 1, prose));
    }
    out
}

/// Link targets on a line: inline `[text](target)` / `![alt](target)` and reference
/// definitions `[label]: target`.
fn targets(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = line;
    while let Some(i) = rest.find("](") {
        let after = &rest[i + 2..];
        let Some(end) = after.find(')') else { break };
        let target = after[..end].split_whitespace().next().unwrap_or("");
        out.push(target.trim_matches(|c| c == '<' || c == '>').to_owned());
        rest = &after[end..];
    }
    let t = line.trim_start();
    if t.starts_with('[')
        && let Some(i) = t.find("]:")
        && let Some(target) = t[i + 2..].split_whitespace().next()
    {
        out.push(target.to_owned());
    }
    out
}

/// GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || *c == ' ' || *c == '-' || *c == '_')
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a markdown file's headings (repeated headings get `-1`, `-2`, … as on GitHub).
fn anchors(text: &str) -> HashSet<String> {
    let mut seen = HashSet::new();
    let mut fenced = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced || !line.starts_with('#') {
            continue;
        }
        let base = slug(line.trim_start_matches('#'));
        let mut s = base.clone();
        let mut n = 0;
        while seen.contains(&s) {
            n += 1;
            s = format!("{base}-{n}");
        }
        seen.insert(s);
    }
    seen
}

/// `path` with `.` and `..` folded, without touching the file system; `None` if it climbs
/// above the start.
fn normalise(path: &Path) -> Option<PathBuf> {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                if !out.pop() {
                    return None;
                }
            }
            other => out.push(other),
        }
    }
    Some(out)
}

/// What is wrong with the links of `file` (whose text is `text`), one message per link.
fn problems(root: &Path, file: &Path, text: &str) -> Vec<String> {
    let name = file
        .strip_prefix(root)
        .unwrap_or(file)
        .display()
        .to_string();
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        if line.contains("../shared") {
            out.push(format!(
                "{name}:{}: points at ../shared, which a clone does not have",
                n + 1
            ));
        }
    }
    let dir = file.parent().unwrap_or(root);
    for (n, line) in prose_lines(text) {
        for target in targets(&line) {
            let here = format!("{name}:{n}: link {target:?}");
            if target.is_empty() || target.contains("://") || target.starts_with("mailto:") {
                continue;
            }
            let (path, anchor) = match target.split_once('#') {
                Some((p, a)) => (p, Some(a)),
                None => (target.as_str(), None),
            };
            if path.is_empty() {
                // An anchor in this very document.
                if !anchors(text).contains(anchor.unwrap_or_default()) {
                    out.push(format!("{here}: no heading with that anchor"));
                }
                continue;
            }
            let resolved = if path.starts_with('/') {
                None
            } else {
                normalise(&dir.join(path)).filter(|p| p.starts_with(root))
            };
            let Some(resolved) = resolved else {
                out.push(format!("{here}: leaves the repository"));
                continue;
            };
            if !resolved.exists() {
                out.push(format!("{here}: no such file"));
                continue;
            }
            if let Some(anchor) = anchor
                && resolved.extension().is_some_and(|e| e == "md")
            {
                let target_text = std::fs::read_to_string(&resolved).unwrap_or_default();
                if !anchors(&target_text).contains(anchor) {
                    out.push(format!("{here}: no heading with that anchor"));
                }
            }
        }
    }
    out
}

#[test]
fn every_document_link_resolves_in_the_repository() {
    let root = Path::new(ROOT);
    let mut all = Vec::new();
    let mut links = 0;
    for file in documents() {
        let text = std::fs::read_to_string(&file).expect("reading a document");
        links += prose_lines(&text)
            .iter()
            .map(|(_, l)| targets(l).len())
            .sum::<usize>();
        all.extend(problems(root, &file, &text));
    }
    assert!(all.is_empty(), "broken document links:\n{}", all.join("\n"));
    // The README links the other guides: if nothing was found, the parser is broken.
    assert!(links >= 3, "only {links} links found");
}

#[test]
fn the_checker_catches_each_kind_of_broken_link() {
    let root = Path::new(ROOT);
    let file = root.join("docs/example.md");
    let text = "# Example heading\n\
                [ok](../README.md) [ok](#example-heading) [ok](performance.md)\n\
                [missing](no-such-file.md) [here](#no-such-heading)\n\
                [anchor](../ARCHITECTURE.md#no-such-heading)\n\
                [outside](../../elsewhere.md)\n\
                see ../shared/DESIGN.md\n\
                ```\n[in code](not-checked.md)\n```\n\
                `[in a span](not-checked.md)`\n\
                [ref]: missing-too.md\n";
    let found = problems(root, &file, text);
    let expect = [
        "docs/example.md:3: link \"no-such-file.md\": no such file",
        "docs/example.md:3: link \"#no-such-heading\": no heading with that anchor",
        "docs/example.md:4: link \"../ARCHITECTURE.md#no-such-heading\": no heading with that anchor",
        "docs/example.md:5: link \"../../elsewhere.md\": leaves the repository",
        "docs/example.md:6: points at ../shared, which a clone does not have",
        "docs/example.md:11: link \"missing-too.md\": no such file",
    ];
    let mut found_sorted = found.clone();
    found_sorted.sort();
    let mut expect = expect.map(str::to_owned).to_vec();
    expect.sort();
    assert_eq!(found_sorted, expect, "{found:#?}");
}

#[test]
fn anchors_follow_github() {
    let a =
        anchors("# Performance\n## Sampler pipeline (`mwb bench sampler`)\n## Notes\n## Notes\n");
    for s in [
        "performance",
        "sampler-pipeline-mwb-bench-sampler",
        "notes",
        "notes-1",
    ] {
        assert!(a.contains(s), "{s} not in {a:?}");
    }
}
