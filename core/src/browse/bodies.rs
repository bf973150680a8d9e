//! Naming objects: turning what a user types after `--objects` — indices, body names from the
//! scene, generator instances such as `block[17]`, a generator's name for all of its instances,
//! or `all` — into object indices, checked against the bodies of the worlds held.
//!
//! Objects are indices into the scene's body order (§4.4.1 lets a query apply to any chosen
//! subset of objects); names are what an animator knows them by. A scene names each
//! `[[body]]`; a generator's instances are `name[i]`, `name[i,j]` or `name[i,j,k]`
//! (`docs/scene-format.md`). The store reports each distinct body list it holds
//! ([`SceneBodies`]); a choice must mean the same indices in every one of them.

use super::api::SceneBodies;

/// Why a list of objects cannot be resolved. Every message names what was typed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ObjectsError {
    #[error("--objects: empty; give indices, body names (e.g. S, block[17]) or all")]
    Empty,
    #[error("--objects: {item:?}: object {index} is out of range: the scene has {count} bodies (0–{last})", last = count.saturating_sub(1))]
    OutOfRange {
        item: String,
        index: u64,
        count: u32,
    },
    #[error("--objects: {item:?}: no body of that name; the scene's bodies are {known}")]
    UnknownName { item: String, known: String },
    #[error("--objects: {item:?}: names are unknown until the stores hold worlds; give indices")]
    NoWorlds { item: String },
    #[error("--objects: {item:?}: the store could not read the scene's body names; give indices")]
    NamesUnknown { item: String },
    #[error(
        "--objects: {item:?} means different bodies in the scenes the stores hold ({first} and \
         {second}); give indices"
    )]
    Ambiguous {
        item: String,
        first: String,
        second: String,
    },
}

/// Splits `text` at the commas that are not inside brackets (`jenga[0,1]` is one item).
pub fn split_items(text: &str) -> Vec<&str> {
    let mut items = Vec::new();
    let (mut depth, mut start) = (0i32, 0);
    for (i, c) in text.char_indices() {
        match c {
            '[' => depth += 1,
            ']' => depth -= 1,
            ',' if depth <= 0 => {
                items.push(text[start..i].trim());
                start = i + 1;
            }
            _ => {}
        }
    }
    items.push(text[start..].trim());
    items.retain(|s| !s.is_empty());
    items
}

/// `name` without white space inside brackets: `block[ 1, 2 ]` is `block[1,2]`.
fn normalised(name: &str) -> String {
    let mut out = String::with_capacity(name.len());
    let mut depth = 0;
    for c in name.chars() {
        match c {
            '[' => depth += 1,
            ']' => depth -= 1,
            c if c.is_whitespace() && depth > 0 => continue,
            _ => {}
        }
        out.push(c);
    }
    out
}

/// The indices `item` names in one body list.
fn resolve_in(item: &str, scene: &SceneBodies) -> Result<Vec<u32>, ObjectsError> {
    if let Ok(index) = item.parse::<u64>() {
        if index >= u64::from(scene.objects) {
            return Err(ObjectsError::OutOfRange {
                item: item.to_owned(),
                index,
                count: scene.objects,
            });
        }
        return Ok(vec![index as u32]);
    }
    if item == "all" {
        return Ok((0..scene.objects).collect());
    }
    if scene.names.is_empty() && scene.objects > 0 {
        return Err(ObjectsError::NamesUnknown {
            item: item.to_owned(),
        });
    }
    let wanted = normalised(item);
    if let Some(i) = scene.names.iter().position(|n| *n == wanted) {
        return Ok(vec![i as u32]);
    }
    // A generator's name alone: every instance of it.
    let prefix = format!("{wanted}[");
    let instances: Vec<u32> = (0..scene.names.len() as u32)
        .filter(|&i| scene.names[i as usize].starts_with(&prefix))
        .collect();
    if !instances.is_empty() {
        return Ok(instances);
    }
    Err(ObjectsError::UnknownName {
        item: item.to_owned(),
        known: known_names(&scene.names),
    })
}

/// The first few names and how many more, for an error message.
fn known_names(names: &[String]) -> String {
    const SHOWN: usize = 12;
    let mut text = names
        .iter()
        .take(SHOWN)
        .map(String::as_str)
        .collect::<Vec<_>>()
        .join(", ");
    if names.len() > SHOWN {
        text += &format!(" … ({} in all)", names.len());
    }
    text
}

/// Resolves `text` (comma-separated items: an index, a body name, a generator instance
/// `name[i]`, a generator's name for all its instances, or `all`) against every body list
/// the stores hold. Indices must be in range in each; names must mean the same indices in
/// each. Without any worlds held, plain indices are taken on trust (a constraint may be drawn
/// before the worlds arrive) and names are refused. The result keeps the order of first
/// mention, without repeats.
pub fn resolve_objects(text: &str, scenes: &[SceneBodies]) -> Result<Vec<u32>, ObjectsError> {
    let items = split_items(text);
    if items.is_empty() {
        return Err(ObjectsError::Empty);
    }
    let mut out: Vec<u32> = Vec::new();
    for item in items {
        let indices = match scenes.split_first() {
            None => match item.parse::<u32>() {
                Ok(i) => vec![i],
                Err(_) => {
                    return Err(ObjectsError::NoWorlds {
                        item: item.to_owned(),
                    });
                }
            },
            Some((first, rest)) => {
                let got = resolve_in(item, first)?;
                for other in rest {
                    let theirs = resolve_in(item, other)?;
                    if theirs != got {
                        return Err(ObjectsError::Ambiguous {
                            item: item.to_owned(),
                            first: describe(&got),
                            second: describe(&theirs),
                        });
                    }
                }
                got
            }
        };
        for i in indices {
            if !out.contains(&i) {
                out.push(i);
            }
        }
    }
    Ok(out)
}

fn describe(indices: &[u32]) -> String {
    let list: Vec<String> = indices.iter().map(u32::to_string).collect();
    format!("object(s) {}", list.join(","))
}

/// `object`'s name in `names` (as `name (#i)`), or `#i` when unnamed: how lists print objects.
pub fn object_label(names: &[String], object: u32) -> String {
    match names.get(object as usize) {
        Some(n) => format!("{n} (#{object})"),
        None => format!("#{object}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(names: &[&str]) -> SceneBodies {
        SceneBodies {
            objects: names.len() as u32,
            names: names.iter().map(|n| (*n).to_owned()).collect(),
            worlds: 1,
        }
    }

    #[test]
    fn names_instances_generators_indices_and_all() {
        let letters = scene(&["S", "block[0]", "block[1]", "block[2]", "jenga[0,1]", "T"]);
        let s = std::slice::from_ref(&letters);
        assert_eq!(resolve_objects("S", s), Ok(vec![0]));
        assert_eq!(resolve_objects("block[2], S", s), Ok(vec![3, 0]));
        assert_eq!(resolve_objects("jenga[0,1]", s), Ok(vec![4]));
        assert_eq!(resolve_objects("jenga[0, 1],T", s), Ok(vec![4, 5]));
        assert_eq!(resolve_objects("block", s), Ok(vec![1, 2, 3]));
        assert_eq!(resolve_objects("1,block[0],5", s), Ok(vec![1, 5]));
        assert_eq!(resolve_objects("all", s), Ok(vec![0, 1, 2, 3, 4, 5]));
        assert_eq!(split_items("a[1,2], b ,,c"), vec!["a[1,2]", "b", "c"]);
    }

    #[test]
    fn refusals_name_the_item_and_the_body_count() {
        let eight = scene(&["A", "B", "C", "D", "E", "F", "G", "H"]);
        let s = std::slice::from_ref(&eight);
        let e = resolve_objects("0,9", s).expect_err("out of range");
        assert_eq!(
            e,
            ObjectsError::OutOfRange {
                item: "9".into(),
                index: 9,
                count: 8
            }
        );
        assert!(
            e.to_string().contains("the scene has 8 bodies (0–7)"),
            "{e}"
        );
        let e = resolve_objects("Q", s).expect_err("unknown");
        assert!(
            e.to_string().contains("\"Q\"") && e.to_string().contains("A, B, C"),
            "{e}"
        );
        assert_eq!(resolve_objects(" , ", s), Err(ObjectsError::Empty));
        // No worlds yet: indices on trust, names refused.
        assert_eq!(resolve_objects("3,9", &[]), Ok(vec![3, 9]));
        assert!(matches!(
            resolve_objects("S", &[]),
            Err(ObjectsError::NoWorlds { .. })
        ));
        // The store could not read the names: indices only.
        let unnamed = SceneBodies {
            objects: 3,
            names: vec![],
            worlds: 2,
        };
        assert_eq!(
            resolve_objects("2", std::slice::from_ref(&unnamed)),
            Ok(vec![2])
        );
        assert!(matches!(
            resolve_objects("S", &[unnamed]),
            Err(ObjectsError::NamesUnknown { .. })
        ));
    }

    #[test]
    fn several_scenes_must_agree() {
        let a = scene(&["S", "T"]);
        let b = scene(&["T", "S", "U"]);
        let both = [a.clone(), b.clone()];
        assert!(matches!(
            resolve_objects("S", &both),
            Err(ObjectsError::Ambiguous { .. })
        ));
        assert_eq!(resolve_objects("0,1", &both), Ok(vec![0, 1]));
        // Index 2 exists in one scene only.
        assert!(matches!(
            resolve_objects("2", &both),
            Err(ObjectsError::OutOfRange { count: 2, .. })
        ));
        assert!(matches!(
            resolve_objects("all", &both),
            Err(ObjectsError::Ambiguous { .. })
        ));
        assert_eq!(object_label(&a.names, 1), "T (#1)");
        assert_eq!(object_label(&[], 4), "#4");
    }
}
