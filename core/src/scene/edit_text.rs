//! Scene edits as text (issue 17): `mwb scene edit`'s `--remove BODY`, `--add-body TABLE` and
//! `--set BODY.FIELD=VALUE`, applied to a scene's TOML so that everything the edits do not touch
//! — comments, blank lines, spelling and order of the other tables — stays as the author wrote
//! it. The edited text is the scene's next revision.
//!
//! Edits address the `[[body]]` tables by `name`. A generator's table (`grid`, `row`, `stack`)
//! is edited as a whole: its instances (`block[1,2,3]`) have no table of their own. Statics,
//! materials, joints and settings are not edited here (an edit of a running job's statics,
//! joints or settings needs a new job; see `mwb_sampler::edit`).
//!
//! ```
//! use mwb_core::scene::edit_text::{TextEdit, apply};
//! use mwb_core::scene::{SceneTemplate, builtin};
//!
//! let edits = [
//!     TextEdit::parse_remove("brick")?,
//!     TextEdit::parse_set("crate.position=[0, 1, 0]")?,
//!     TextEdit::parse_add(
//!         r#"{ name = "ball", shape = "sphere", radius = 0.1, material = "wood", position = [0, 2, 0] }"#,
//!     )?,
//! ];
//! let edited = apply(builtin::TUMBLE, "scenes/tumble.toml", &edits)?;
//! // Untouched lines stay as written, comments included.
//! assert!(edited.starts_with("# tumble — five boxes of mixed sizes thrown onto the ground.\n"));
//! assert!(edited.contains("\nposition = [0, 1, 0]\n"));
//!
//! let world = SceneTemplate::parse(&edited, "scenes/tumble.toml")?.instantiate(7);
//! let names: Vec<&str> = world.bodies.iter().map(|b| b.name.as_str()).collect();
//! assert_eq!(names, ["crate", "plank", "die", "slab", "ball"]);
//! assert_eq!(world.bodies[0].position, [0.0, 1.0, 0.0]);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::fmt;

use toml_edit::{ArrayOfTables, DocumentMut, Item, Table, TableLike, TomlError, Value};

use super::error::SceneError;
use super::model::SimPreset;
use super::template::SceneTemplate;
use super::toml_span::Source;

/// The keys that make a `[[body]]` or `[[static]]` table a generator (docs/scene-format.md
/// "Generators"; the parser's own list is private to `parse.rs`).
const GENERATOR_KEYS: [&str; 3] = ["grid", "row", "stack"];

/// At most this many body names are listed when a name is not found.
const LISTED_NAMES: usize = 8;

/// The command-line flag an edit came from; errors name it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EditFlag {
    /// `--set BODY.FIELD=VALUE`
    Set,
    /// `--remove BODY`
    Remove,
    /// `--add-body TABLE`
    AddBody,
}

impl EditFlag {
    /// The flag as typed: `--set`, `--remove`, `--add-body`.
    pub const fn as_str(self) -> &'static str {
        match self {
            EditFlag::Set => "--set",
            EditFlag::Remove => "--remove",
            EditFlag::AddBody => "--add-body",
        }
    }
}

impl fmt::Display for EditFlag {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// One edit of a scene's `[[body]]` tables.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TextEdit {
    /// Remove the `[[body]]` table with this name (a generator: all its instances).
    Remove { body: String },
    /// Append a body: a TOML inline table (`{ name = "ball", shape = "sphere", … }`), the
    /// `key = value` lines of a table, or a `[[body]]` table with its `[[body.part]]`s.
    Add { table: String },
    /// Set `field` of the `[[body]]` table `body` to the TOML value `value` (`[0, 1, 0]`, `0.5`,
    /// `"steel"`), replacing the key or adding it. `field` may be a dotted path into a table the
    /// body has (`row.count`, `axis_angle.deg`).
    Set {
        body: String,
        field: String,
        value: String,
    },
}

impl TextEdit {
    /// `--set BODY.FIELD=VALUE`: `crate.position=[0, 1, 0]`, `ball.material="steel"`,
    /// `row.count=2` style paths (`block.grid.count=[2, 2, 2]`). `BODY.FIELD` is a TOML dotted
    /// key, so a name with dots or spaces is quoted: `"my box".radius=0.1`.
    pub fn parse_set(arg: &str) -> Result<TextEdit, TextEditError> {
        let syntax = |problem: &str| TextEditError::Syntax {
            flag: EditFlag::Set,
            arg: arg.to_owned(),
            problem: problem.to_owned(),
        };
        let Some((path, value)) = split_assignment(arg) else {
            return Err(syntax(
                "expected BODY.FIELD=VALUE, e.g. crate.position=[0, 1, 0]",
            ));
        };
        let path = path.trim();
        let (body, field) = match path.rfind("].") {
            // A generated name (`block[1,2,3].position`) is no TOML key; it is taken as written
            // so that `apply` can say which generator makes it.
            Some(end) if !path.starts_with(['"', '\'']) => {
                (path[..=end].to_owned(), path[end + 2..].to_owned())
            }
            _ => {
                let keys = toml_edit::Key::parse(path).map_err(|_| {
                    syntax("the part before `=` is not BODY.FIELD (quote a name with dots or spaces: \"my box\".radius=0.1)")
                })?;
                let [body, field @ ..] = keys.as_slice() else {
                    return Err(syntax("expected BODY.FIELD before `=`"));
                };
                let field: Vec<&str> = field.iter().map(|k| k.get()).collect();
                (body.get().to_owned(), field.join("."))
            }
        };
        if field.is_empty() {
            return Err(syntax(
                "no field: expected BODY.FIELD=VALUE, e.g. crate.position=[0, 1, 0]",
            ));
        }
        let value = value.trim();
        parse_value(EditFlag::Set, arg, value)?;
        Ok(TextEdit::Set {
            body,
            field,
            value: value.to_owned(),
        })
    }

    /// `--remove BODY`: the name as written in the body's `name` (no quoting).
    pub fn parse_remove(arg: &str) -> Result<TextEdit, TextEditError> {
        let body = arg.trim();
        if body.is_empty() {
            return Err(TextEditError::Syntax {
                flag: EditFlag::Remove,
                arg: arg.to_owned(),
                problem: "expected the name of a [[body]]".to_owned(),
            });
        }
        Ok(TextEdit::Remove {
            body: body.to_owned(),
        })
    }

    /// `--add-body TABLE`: checked to be one TOML table with a `name` string.
    pub fn parse_add(arg: &str) -> Result<TextEdit, TextEditError> {
        body_table(arg)?;
        Ok(TextEdit::Add {
            table: arg.to_owned(),
        })
    }

    /// The flag this edit is written with.
    pub fn flag(&self) -> EditFlag {
        match self {
            TextEdit::Remove { .. } => EditFlag::Remove,
            TextEdit::Add { .. } => EditFlag::AddBody,
            TextEdit::Set { .. } => EditFlag::Set,
        }
    }
}

/// Displays as the command-line argument: `--set crate.position=[0, 1, 0]`.
impl fmt::Display for TextEdit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let flag = self.flag();
        match self {
            TextEdit::Remove { body } => write!(f, "{flag} {body}"),
            TextEdit::Add { table } => write!(f, "{flag} {table}"),
            TextEdit::Set { body, field, value } => write!(f, "{flag} {body}.{field}={value}"),
        }
    }
}

/// Why an edit was refused.
#[derive(Debug, thiserror::Error)]
pub enum TextEditError {
    /// A flag's argument is not of the flag's form.
    #[error("{flag} {arg}: {problem}")]
    Syntax {
        flag: EditFlag,
        arg: String,
        problem: String,
    },
    /// A value (`--set`) or table (`--add-body`) that is not TOML.
    #[error("{flag} {arg}: {what} is not TOML: {message}")]
    NotToml {
        flag: EditFlag,
        arg: String,
        /// `the value` or `the table`.
        what: &'static str,
        /// The first line of the TOML parser's message, with a hint where one helps.
        message: String,
        #[source]
        source: Box<TomlError>,
    },
    /// The text to edit is not TOML, or its `body` is not an array of `[[body]]` tables.
    #[error("the scene to edit: {0}")]
    Scene(SceneError),
    /// No `[[body]]` table has this name.
    #[error("{flag} {body}: no [[body]] named \"{body}\" in {file} (its [[body]] tables: {known})")]
    UnknownBody {
        flag: EditFlag,
        body: String,
        file: String,
        /// The first names of the file's `[[body]]` tables, or `none`.
        known: String,
    },
    /// The name is a static's (or a static generator's instance's).
    #[error(
        "{flag} {body}: \"{body}\" is a [[static]] in {file}, not a [[body]]: static geometry \
         is not edited in a running job (it needs a new job)"
    )]
    Static {
        flag: EditFlag,
        body: String,
        file: String,
    },
    /// The body is an instance of a generator: it has no table of its own.
    #[error(
        "{flag} {body}: body \"{body}\" comes from the generator \"{generator}\" (`{layout}`) in \
         {file} and has no table of its own: edit the generator (`--set {generator}.FIELD=…`, \
         `--remove {generator}`: all its instances) or give a whole revision file"
    )]
    Generated {
        flag: EditFlag,
        body: String,
        generator: String,
        /// `grid`, `row` or `stack`.
        layout: &'static str,
        file: String,
    },
    /// `--add-body` of a name a body or static already has.
    #[error(
        "{flag} {name}: a {kind} named \"{name}\" is already in {file}: choose another name \
         (names are unique across bodies and statics)"
    )]
    Duplicate {
        flag: EditFlag,
        name: String,
        /// `[[body]]` or `[[static]]`.
        kind: &'static str,
        file: String,
    },
    /// `--set BODY.A.B=…` where the body has no table `A`.
    #[error("{flag} {body}.{field}: body \"{body}\" has no table `{table}` to set `{field}` in")]
    NoTable {
        flag: EditFlag,
        body: String,
        field: String,
        /// The missing (or non-table) part of the path.
        table: String,
    },
    /// The edited text is not a valid scene. The error's line is a line of the edited text.
    #[error("the edited scene is invalid: {0}")]
    Invalid(SceneError),
}

/// Applies `edits` in order to the scene `text` and validates the result with
/// [`SceneTemplate::parse`]; returns the edited text. `file` names the scene in errors.
///
/// The text must be resolved (no `shape = "mesh"`: `mwb_mesh::resolve`), as for any parse; for
/// a text with meshes use [`apply_unvalidated`], resolve, then parse.
pub fn apply(text: &str, file: &str, edits: &[TextEdit]) -> Result<String, TextEditError> {
    let out = apply_unvalidated(text, file, edits)?;
    // Validated once, after all edits: the scene between two edits may be invalid on its own
    // (`--set b.shape="capsule" --set b.height=0.3` passes through a capsule without a height).
    SceneTemplate::parse(&out, file).map_err(TextEditError::Invalid)?;
    Ok(out)
}

/// [`apply`] without the final validation: for a caller that must transform the edited text
/// before it can be parsed (resolving the meshes of an added body), and then validates it.
pub fn apply_unvalidated(
    text: &str,
    file: &str,
    edits: &[TextEdit],
) -> Result<String, TextEditError> {
    let src = Source { text, file };
    let doc = toml_edit::Document::parse(text).map_err(|e| {
        let message = first_line(e.message());
        TextEditError::Scene(src.error(e.span(), None, None, format!("invalid TOML: {message}")))
    })?;
    // An inline array `body = [{ … }]` is valid for the parser, but edits are of [[body]]
    // tables (said here, while the document still knows where `body` was written).
    if let Some(other) = doc.get("body").filter(|b| !b.is_array_of_tables()) {
        return Err(TextEditError::Scene(src.error(
            other.span(),
            Some("scene".to_owned()),
            Some("body".to_owned()),
            format!(
                "the bodies are written as {}, not as [[body]] tables: only [[body]] tables are \
                 edited (write them so, or give a whole revision file)",
                other.type_name()
            ),
        )));
    }
    let mut doc = doc.into_mut();
    for edit in edits {
        match edit {
            TextEdit::Remove { body } => remove(&mut doc, file, body)?,
            TextEdit::Add { table } => add(&mut doc, file, table)?,
            TextEdit::Set { body, field, value } => {
                set(&mut doc, file, body, field, value)?;
            }
        }
    }
    let out = doc.to_string();
    // toml_edit ends every line it writes with `\n`; a file written with `\r\n` keeps them.
    if text.contains("\r\n") {
        return Ok(out.replace("\r\n", "\n").replace('\n', "\r\n"));
    }
    Ok(out)
}

// ---- the three edits ----

fn remove(doc: &mut DocumentMut, file: &str, body: &str) -> Result<(), TextEditError> {
    let index = find_body(doc, file, EditFlag::Remove, body)?;
    let bodies = body_tables_mut(doc).ok_or_else(|| unreachable_missing(file))?;
    let removed = bodies.remove(index);
    // The comment lines right above a body's header are its own and go with it; a paragraph
    // separated from the header by a blank line heads what follows, so it stays.
    let detached = detached_comments(removed.decor().prefix().and_then(|p| p.as_str()));
    if !detached.is_empty() {
        let position = removed.position().unwrap_or(isize::MAX);
        prepend_to_next_table(doc, position, detached);
    }
    Ok(())
}

fn add(doc: &mut DocumentMut, file: &str, table: &str) -> Result<(), TextEditError> {
    let (new, name) = body_table(table)?;
    let duplicate = |kind| TextEditError::Duplicate {
        flag: EditFlag::AddBody,
        name: name.clone(),
        kind,
        file: file.to_owned(),
    };
    if entries(doc, "body").any(|t| name_of(t) == Some(&name)) {
        return Err(duplicate("[[body]]"));
    }
    if entries(doc, "static").any(|t| name_of(t) == Some(&name)) {
        return Err(duplicate("[[static]]"));
    }
    match body_tables_mut(doc) {
        Some(bodies) => bodies.push(new),
        None => {
            let mut bodies = ArrayOfTables::new();
            bodies.push(new);
            doc.insert("body", Item::ArrayOfTables(bodies));
        }
    }
    Ok(())
}

fn set(
    doc: &mut DocumentMut,
    file: &str,
    body: &str,
    field: &str,
    value: &str,
) -> Result<(), TextEditError> {
    let arg = format!("{body}.{field}={value}");
    let mut value = parse_value(EditFlag::Set, &arg, value.trim())?;
    let index = find_body(doc, file, EditFlag::Set, body)?;
    let bodies = body_tables_mut(doc).ok_or_else(|| unreachable_missing(file))?;
    let mut target: &mut dyn TableLike = bodies
        .get_mut(index)
        .ok_or_else(|| unreachable_missing(file))?;
    let path: Vec<&str> = field.split('.').collect();
    let (key, parents) = path.split_last().unwrap_or((&field, &[]));
    for (depth, parent) in parents.iter().enumerate() {
        target = target
            .get_mut(parent)
            .and_then(Item::as_table_like_mut)
            .ok_or_else(|| TextEditError::NoTable {
                flag: EditFlag::Set,
                body: body.to_owned(),
                field: field.to_owned(),
                table: path[..=depth].join("."),
            })?;
    }
    match target.get_mut(key) {
        Some(item) => {
            // The old value's decor holds the spaces around it and a trailing `# comment`.
            if let Some(old) = item.as_value() {
                *value.decor_mut() = old.decor().clone();
            }
            *item = Item::Value(value);
        }
        None => {
            target.insert(key, Item::Value(value));
        }
    }
    Ok(())
}

// ---- finding bodies ----

/// Index of the `[[body]]` table named `body`, or why there is none.
fn find_body(
    doc: &DocumentMut,
    file: &str,
    flag: EditFlag,
    body: &str,
) -> Result<usize, TextEditError> {
    if let Some(bodies) = body_tables(doc)
        && let Some(index) = bodies.iter().position(|t| name_of(t) == Some(body))
    {
        return Ok(index);
    }
    let static_error = || TextEditError::Static {
        flag,
        body: body.to_owned(),
        file: file.to_owned(),
    };
    if entries(doc, "static").any(|t| name_of(t) == Some(body)) {
        return Err(static_error());
    }
    // Generated names are `name[i]`, `name[i,j]`, `name[i,j,k]`; plain names have no brackets.
    if let Some((base, _)) = body.strip_suffix(']').and_then(|b| b.split_once('[')) {
        if let Some(layout) = entries(doc, "body")
            .find(|t| name_of(*t) == Some(base))
            .and_then(generator_of)
        {
            return Err(TextEditError::Generated {
                flag,
                body: body.to_owned(),
                generator: base.to_owned(),
                layout,
                file: file.to_owned(),
            });
        }
        if entries(doc, "static").any(|t| name_of(t) == Some(base) && generator_of(t).is_some()) {
            return Err(static_error());
        }
    }
    let names: Vec<&str> = entries(doc, "body").filter_map(name_of).collect();
    let mut known = names
        .iter()
        .take(LISTED_NAMES)
        .copied()
        .collect::<Vec<_>>()
        .join(", ");
    if names.is_empty() {
        known = "none".to_owned();
    } else if names.len() > LISTED_NAMES {
        known = format!("{known}, … ({} in all)", names.len());
    }
    Err(TextEditError::UnknownBody {
        flag,
        body: body.to_owned(),
        file: file.to_owned(),
        known,
    })
}

/// The `[[body]]` tables, `None` if the scene has none (`apply_unvalidated` refused any other
/// kind of `body`).
fn body_tables(doc: &DocumentMut) -> Option<&ArrayOfTables> {
    doc.get("body").and_then(Item::as_array_of_tables)
}

fn body_tables_mut(doc: &mut DocumentMut) -> Option<&mut ArrayOfTables> {
    doc.get_mut("body").and_then(Item::as_array_of_tables_mut)
}

/// A found index vanished between finding and editing: cannot happen (nothing runs between).
fn unreachable_missing(file: &str) -> TextEditError {
    TextEditError::Scene(SceneError {
        file: file.to_owned(),
        line: None,
        item: None,
        field: Some("body".to_owned()),
        message: "the [[body]] tables changed while being edited".to_owned(),
    })
}

/// The entries of `[[key]]` tables or of an inline `key = [{ … }]` array, for reading names.
fn entries<'d>(
    doc: &'d DocumentMut,
    key: &str,
) -> Box<dyn Iterator<Item = &'d dyn TableLike> + 'd> {
    match doc.get(key) {
        Some(Item::ArrayOfTables(tables)) => Box::new(tables.iter().map(|t| t as &dyn TableLike)),
        Some(Item::Value(Value::Array(values))) => Box::new(
            values
                .iter()
                .filter_map(Value::as_inline_table)
                .map(|t| t as &dyn TableLike),
        ),
        _ => Box::new(std::iter::empty()),
    }
}

fn name_of(table: &dyn TableLike) -> Option<&str> {
    table.get("name").and_then(Item::as_str)
}

/// The generator key of a body or static table (`grid`, `row`, `stack`), if it is one.
fn generator_of(table: &dyn TableLike) -> Option<&'static str> {
    GENERATOR_KEYS.into_iter().find(|k| table.contains_key(k))
}

// ---- text helpers ----

/// Splits `BODY.FIELD=VALUE` at the first `=` outside a quoted key.
fn split_assignment(arg: &str) -> Option<(&str, &str)> {
    let mut quote: Option<char> = None;
    let mut escaped = false;
    for (i, c) in arg.char_indices() {
        match quote {
            Some('"') if escaped => escaped = false,
            Some('"') if c == '\\' => escaped = true,
            Some(q) if c == q => quote = None,
            Some(_) => {}
            None if c == '"' || c == '\'' => quote = Some(c),
            None if c == '=' => return Some((&arg[..i], &arg[i + 1..])),
            None => {}
        }
    }
    None
}

fn parse_value(flag: EditFlag, arg: &str, value: &str) -> Result<Value, TextEditError> {
    value.parse::<Value>().map_err(|source| {
        let mut message = first_line(source.message());
        if value.is_empty() {
            message = "no value after `=`".to_owned();
        } else if value
            .chars()
            .all(|c| c.is_alphanumeric() || c == '_' || c == '-')
        {
            // The shell ate the quotes of `--set ball.material="steel"`.
            message.push_str(&format!(
                " (a string needs quotes, which the shell removes unless the argument is in \
                 single quotes: '…=\"{value}\"')"
            ));
        }
        TextEditError::NotToml {
            flag,
            arg: arg.to_owned(),
            what: "the value",
            message,
            source: Box::new(source),
        }
    })
}

/// The body an `--add-body` argument describes, ready to append, and its name.
fn body_table(arg: &str) -> Result<(Table, String), TextEditError> {
    let syntax = |problem: &str| TextEditError::Syntax {
        flag: EditFlag::AddBody,
        arg: arg.to_owned(),
        problem: problem.to_owned(),
    };
    let not_toml = |source: TomlError| TextEditError::NotToml {
        flag: EditFlag::AddBody,
        arg: arg.to_owned(),
        what: "the table",
        message: first_line(source.message()),
        source: Box::new(source),
    };
    let trimmed = arg.trim();
    let mut table = if trimmed.starts_with('{') {
        let Value::InlineTable(inline) = trimmed.parse::<Value>().map_err(not_toml)? else {
            return Err(syntax(
                "expected one table: { name = \"…\", shape = \"…\", … }",
            ));
        };
        inline.into_table()
    } else {
        let doc: DocumentMut = trimmed.parse().map_err(not_toml)?;
        let root = doc.into_table();
        match root.get("body") {
            // `[[body]]` form: exactly one body and nothing else.
            Some(Item::ArrayOfTables(bodies)) if root.len() == 1 => match bodies.len() {
                1 => bodies.get(0).cloned().unwrap_or_default(),
                _ => return Err(syntax("give one [[body]] per --add-body")),
            },
            _ => root,
        }
    };
    let Some(name) = table.get("name").and_then(Item::as_str).map(str::to_owned) else {
        return Err(syntax("the table has no `name = \"…\"`"));
    };
    // Positions order tables when the document is written; the new body's come from another
    // text. Without one it is written after the table written before it: the last body.
    clear_positions(&mut table);
    let prefix = table
        .decor()
        .prefix()
        .and_then(|p| p.as_str())
        .unwrap_or("")
        .trim_start_matches(['\n', '\r'])
        .to_owned();
    table.decor_mut().set_prefix(format!("\n{prefix}"));
    Ok((table, name))
}

fn clear_positions(table: &mut Table) {
    table.set_position(None);
    for (_, item) in table.iter_mut() {
        match item {
            Item::Table(t) => clear_positions(t),
            Item::ArrayOfTables(tables) => tables.iter_mut().for_each(clear_positions),
            _ => {}
        }
    }
}

/// The part of a table header's prefix that ends at its last blank line, if it holds a comment:
/// `"\n# Section\n\n# this body\n"` → `"\n# Section\n"`.
fn detached_comments(prefix: Option<&str>) -> String {
    let prefix = prefix.unwrap_or("");
    let mut start = 0;
    let mut last_blank = None;
    for line in prefix.split_inclusive('\n') {
        if line.trim().is_empty() {
            last_blank = Some(start);
        }
        start += line.len();
    }
    match last_blank {
        Some(end) if prefix[..end].contains('#') => prefix[..end].to_owned(),
        _ => String::new(),
    }
}

/// Puts `text` in front of the header of the first table written after `position`, or at the
/// end of the document if none is.
fn prepend_to_next_table(doc: &mut DocumentMut, position: isize, text: String) {
    let mut next: Option<isize> = None;
    visit_tables(doc.as_table_mut(), &mut |t| {
        if let Some(p) = t.position()
            && p > position
            && next.is_none_or(|n| p < n)
        {
            next = Some(p);
        }
    });
    let Some(next) = next else {
        let trailing = doc.trailing().as_str().unwrap_or("").to_owned();
        doc.set_trailing(format!("{text}{trailing}"));
        return;
    };
    let mut text = Some(text);
    visit_tables(doc.as_table_mut(), &mut |t| {
        if t.position() == Some(next)
            && let Some(text) = text.take()
        {
            let own = t.decor().prefix().and_then(|p| p.as_str()).unwrap_or("");
            let joined = format!("{text}{own}");
            t.decor_mut().set_prefix(joined);
        }
    });
}

fn visit_tables(table: &mut Table, f: &mut dyn FnMut(&mut Table)) {
    f(table);
    for (_, item) in table.iter_mut() {
        match item {
            Item::Table(t) => visit_tables(t, f),
            Item::ArrayOfTables(tables) => {
                for t in tables.iter_mut() {
                    visit_tables(t, f);
                }
            }
            _ => {}
        }
    }
}

/// A TOML parser message on one line (the first; `file:line` or the flag says where).
/// Sets the scene's simulation preset (`[settings] sim`, issue 19) in its text, keeping
/// everything else as written; a scene without `[settings]` gets the table at its end (so the
/// author's line numbers stay true). Used by `--sim` and to record what `sim = "auto"` chose:
/// `note` becomes a comment after the value.
///
/// ```
/// use mwb_core::scene::edit_text::set_sim_preset;
/// use mwb_core::scene::{SceneTemplate, SimPreset, builtin};
///
/// let text = set_sim_preset(builtin::TUMBLE, "scenes/tumble.toml", SimPreset::Draft, None)?;
/// assert!(text.starts_with("# tumble"));
/// let scene = SceneTemplate::parse(&text, "scenes/tumble.toml")?.instantiate(0);
/// assert_eq!(scene.settings.sim, SimPreset::Draft);
/// assert_eq!(scene.settings.solver_iterations, 1);
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn set_sim_preset(
    text: &str,
    file: &str,
    preset: SimPreset,
    note: Option<&str>,
) -> Result<String, TextEditError> {
    let src = Source { text, file };
    let mut doc = text.parse::<DocumentMut>().map_err(|e| {
        let message = first_line(e.message());
        TextEditError::Scene(src.error(e.span(), None, None, format!("invalid TOML: {message}")))
    })?;
    let mut value = Value::from(preset.name());
    if let Some(note) = note {
        let note = note.replace(['\n', '\r'], " ");
        value.decor_mut().set_suffix(format!(" # {note}"));
    }
    match doc.get_mut("settings") {
        None => {
            let mut t = Table::new();
            t.insert("sim", Item::Value(value));
            doc.insert("settings", Item::Table(t));
        }
        Some(item) => match item.as_table_like_mut() {
            Some(t) => {
                // Keep the decoration (spacing, a trailing comment) of a line being replaced.
                match t.get_mut("sim").and_then(Item::as_value_mut) {
                    Some(old) => {
                        // Keep the author's comment unless there is a note to write.
                        if note.is_none() {
                            let decor = old.decor().clone();
                            *value.decor_mut() = decor;
                        }
                        *old = value;
                    }
                    None => {
                        t.insert("sim", Item::Value(value));
                    }
                }
            }
            None => {
                return Err(TextEditError::Scene(src.error(
                    item.span(),
                    Some("scene".to_owned()),
                    Some("settings".to_owned()),
                    format!("expected a table, found {}", item.type_name()),
                )));
            }
        },
    }
    let mut out = doc.to_string();
    if text.contains("\r\n") {
        out = out.replace("\r\n", "\n").replace('\n', "\r\n");
    }
    SceneTemplate::parse(&out, file).map_err(TextEditError::Invalid)?;
    Ok(out)
}

fn first_line(message: &str) -> String {
    message
        .lines()
        .next()
        .unwrap_or("invalid TOML")
        .trim()
        .to_owned()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Scene, builtin};
    use proptest::prelude::*;

    const BALL: &str = r#"{ name = "ball", shape = "sphere", radius = 0.1, material = "wood", position = [0, 2, 0] }"#;

    /// A body hung from the world by a joint.
    const JOINTED: &str = "name = \"j\"\n\n[[material]]\nname = \"m\"\n\n[[body]]\nname = \"a\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"m\"\nposition = [0, 1, 0]\n\n# The hinge.\n[[joint]]\nname = \"h\"\nkind = \"spherical\"\nbody1 = \"world\"\nbody2 = \"a\"\n";

    #[test]
    fn the_preset_is_set_where_the_author_would_write_it() {
        let sim = |text: &str, p| {
            set_sim_preset(text, "t.toml", p, None).unwrap_or_else(|e| panic!("{e}"))
        };
        // No [settings]: a table at the end, every line before it unchanged.
        let out = sim(JOINTED, SimPreset::Final);
        assert!(out.starts_with(JOINTED), "{out}");
        assert!(out.ends_with("[settings]\nsim = \"final\"\n"), "{out}");
        // An existing key is replaced in place, its comment kept; other settings stay.
        let text = "name = \"j\"\n[settings]\nsim = \"draft\" # quick look\nend_time = 2\n";
        let out = sim(
            &text.replace("name = \"j\"\n", JOINTED),
            SimPreset::Standard,
        );
        assert!(
            out.contains("sim = \"standard\" # quick look\nend_time = 2\n"),
            "{out}"
        );
        // An inline table.
        let inline = JOINTED.replacen(
            "name = \"j\"\n",
            "name = \"j\"\nsettings = { end_time = 2 }\n",
            1,
        );
        let out = sim(&inline, SimPreset::Draft);
        let scene = SceneTemplate::parse(&out, "t.toml")
            .unwrap_or_else(|e| panic!("{e}"))
            .instantiate(0);
        assert_eq!(
            (scene.settings.sim, scene.settings.end_time),
            (SimPreset::Draft, 2.0)
        );
        // CRLF files stay CRLF.
        let crlf = JOINTED.replace('\n', "\r\n");
        let out = sim(&crlf, SimPreset::Draft);
        assert!(!out.replace("\r\n", "").contains('\n'), "{out:?}");
        // A scene whose settings are not a table is refused.
        let bad = JOINTED.replacen("name = \"j\"\n", "name = \"j\"\nsettings = 3\n", 1);
        assert!(set_sim_preset(&bad, "t.toml", SimPreset::Draft, None).is_err());
        // A note is a comment after the value.
        let out = set_sim_preset(
            JOINTED,
            "t.toml",
            SimPreset::Draft,
            Some("chosen by auto\nx"),
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert!(
            out.ends_with("sim = \"draft\" # chosen by auto x\n"),
            "{out}"
        );
    }

    fn edit(text: &str, edits: &[TextEdit]) -> String {
        apply(text, "test.toml", edits).unwrap_or_else(|e| panic!("{e}"))
    }

    fn refused(text: &str, edits: &[TextEdit]) -> String {
        match apply(text, "test.toml", edits) {
            Ok(out) => panic!("expected a refusal, got:\n{out}"),
            Err(e) => e.to_string(),
        }
    }

    fn world(text: &str) -> Scene {
        SceneTemplate::parse(text, "test.toml")
            .unwrap_or_else(|e| panic!("{e}"))
            .instantiate(3)
    }

    fn set(arg: &str) -> TextEdit {
        TextEdit::parse_set(arg).unwrap_or_else(|e| panic!("{e}"))
    }

    fn remove(body: &str) -> TextEdit {
        TextEdit::parse_remove(body).unwrap_or_else(|e| panic!("{e}"))
    }

    fn add(table: &str) -> TextEdit {
        TextEdit::parse_add(table).unwrap_or_else(|e| panic!("{e}"))
    }

    /// `text` without the bytes from the first `from` up to the first `to` after it.
    fn cut(text: &str, from: &str, to: &str) -> String {
        let start = text
            .find(from)
            .unwrap_or_else(|| panic!("{from:?} not in text"));
        let end = start
            + text[start..]
                .find(to)
                .unwrap_or_else(|| panic!("{to:?} not after {from:?}"));
        format!("{}{}", &text[..start], &text[end..])
    }

    /// The lines of `a` and `b` that differ (same number of lines expected).
    fn changed_lines<'a>(a: &'a str, b: &'a str) -> Vec<(&'a str, &'a str)> {
        assert_eq!(a.lines().count(), b.lines().count(), "{b}");
        a.lines().zip(b.lines()).filter(|(x, y)| x != y).collect()
    }

    /// The module's example, run here too (it is a doctest; this keeps it checked by `--lib`).
    #[test]
    fn the_module_example_holds() {
        let edits = [remove("brick"), set("crate.position=[0, 1, 0]"), add(BALL)];
        let edited = edit(builtin::TUMBLE, &edits);
        assert!(
            edited.starts_with("# tumble — five boxes of mixed sizes thrown onto the ground.\n")
        );
        assert!(edited.contains("\nposition = [0, 1, 0]\n"));
        let world = world(&edited);
        let names: Vec<&str> = world.bodies.iter().map(|b| b.name.as_str()).collect();
        assert_eq!(names, ["crate", "plank", "die", "slab", "ball"]);
        assert_eq!(world.bodies[0].position, [0.0, 1.0, 0.0]);
    }

    /// The example commands of docs/scene-format.md "Editing a scene" do what the text says.
    #[test]
    fn the_documented_edits_apply_to_pachinko() {
        let doc = include_str!("../../../docs/scene-format.md");
        let section = doc
            .split("## Editing a scene")
            .nth(1)
            .and_then(|s| s.split("```sh\n").nth(1))
            .and_then(|s| s.split("```").next())
            .unwrap_or_default();
        let mut edits = Vec::new();
        for line in section.lines() {
            let words = shell_words(line);
            for pair in words.windows(2) {
                match pair[0].as_str() {
                    "--remove" => edits.push(remove(&pair[1])),
                    "--add-body" => edits.push(add(&pair[1])),
                    "--set" => edits.push(set(&pair[1])),
                    _ => {}
                }
            }
        }
        assert_eq!(edits.len(), 5, "{section}");
        let w = world(&edit(builtin::PACHINKO, &edits));
        let names: Vec<&str> = w.bodies.iter().map(|b| b.name.as_str()).collect();
        assert_eq!(names, ["ball[0]", "ball[1]", "die[0]", "die[1]", "marble"]);
        assert!(
            w.bodies[2..4]
                .iter()
                .all(|b| w.materials[b.material].name == "ball")
        );
    }

    /// Words of a shell line: spaces split, single quotes group.
    fn shell_words(line: &str) -> Vec<String> {
        let mut words = Vec::new();
        let mut word: Option<String> = None;
        let mut quoted = false;
        for c in line.chars() {
            match c {
                '\'' => {
                    quoted = !quoted;
                    word.get_or_insert_default();
                }
                ' ' if !quoted => words.extend(word.take()),
                c => word.get_or_insert_default().push(c),
            }
        }
        words.extend(word);
        words
    }

    // ---- the flags ----

    #[test]
    fn flags_parse_into_edits() {
        assert_eq!(
            set("crate.position=[0,1,0]"),
            TextEdit::Set {
                body: "crate".into(),
                field: "position".into(),
                value: "[0,1,0]".into()
            }
        );
        assert_eq!(
            set(r#" "my box".material = "steel" "#),
            TextEdit::Set {
                body: "my box".into(),
                field: "material".into(),
                value: "\"steel\"".into()
            }
        );
        assert_eq!(
            set("block.grid.count=[2, 2, 2]"),
            TextEdit::Set {
                body: "block".into(),
                field: "grid.count".into(),
                value: "[2, 2, 2]".into()
            }
        );
        // `=` inside a quoted name is part of the name.
        assert_eq!(
            set(r#""a=b".radius=0.5"#),
            TextEdit::Set {
                body: "a=b".into(),
                field: "radius".into(),
                value: "0.5".into()
            }
        );
        assert_eq!(
            remove(" brick "),
            TextEdit::Remove {
                body: "brick".into()
            }
        );
        assert_eq!(add(BALL), TextEdit::Add { table: BALL.into() });
        assert_eq!(
            set("crate.position=[0, 1, 0]").to_string(),
            "--set crate.position=[0, 1, 0]"
        );
        assert_eq!(remove("brick").to_string(), "--remove brick");
    }

    #[test]
    fn malformed_flags_are_refused_naming_the_flag_and_the_problem() {
        let cases: &[(Result<TextEdit, TextEditError>, &str)] = &[
            (
                TextEdit::parse_set("crate.position"),
                "--set crate.position: expected BODY.FIELD=VALUE",
            ),
            (
                TextEdit::parse_set("crate=[0, 1, 0]"),
                "--set crate=[0, 1, 0]: no field",
            ),
            (
                TextEdit::parse_set("cr ate.x=1"),
                "--set cr ate.x=1: the part before `=` is not BODY.FIELD",
            ),
            (
                TextEdit::parse_set("crate.position="),
                "--set crate.position=: the value is not TOML: no value after `=`",
            ),
            (
                TextEdit::parse_set("crate.position=[0, 1"),
                "--set crate.position=[0, 1: the value is not TOML: unclosed array, expected `]`",
            ),
            (
                TextEdit::parse_set("crate.material=steel"),
                "the value is not TOML: ",
            ),
            (
                TextEdit::parse_remove("  "),
                "--remove   : expected the name of a [[body]]",
            ),
            (
                TextEdit::parse_add("{ name = \"b\", "),
                "--add-body { name = \"b\", : the table is not TOML",
            ),
            (
                TextEdit::parse_add("[1, 2]"),
                "--add-body [1, 2]: the table is not TOML",
            ),
            (
                TextEdit::parse_add("{ shape = \"sphere\" }"),
                "--add-body { shape = \"sphere\" }: the table has no `name = \"…\"`",
            ),
            (
                TextEdit::parse_add("[[body]]\nname = \"a\"\n[[body]]\nname = \"b\"\n"),
                "give one [[body]] per --add-body",
            ),
        ];
        for (result, expected) in cases {
            match result {
                Ok(edit) => panic!("{edit:?} should be refused ({expected})"),
                Err(e) => assert!(
                    e.to_string().contains(expected),
                    "{e}\nexpected: {expected}"
                ),
            }
        }
        // The bare word of a string whose quotes the shell removed gets a hint.
        let e = TextEdit::parse_set("crate.material=steel")
            .map(|_| ())
            .unwrap_err();
        assert!(e.to_string().contains("a string needs quotes"), "{e}");
        assert!(
            std::error::Error::source(&e).is_some(),
            "keeps the TOML error"
        );
    }

    // ---- remove ----

    #[test]
    fn remove_takes_out_exactly_the_body_table() {
        let text = builtin::TUMBLE;
        let out = edit(text, &[remove("brick")]);
        let expected = cut(
            text,
            "\n[[body]]\nname = \"brick\"",
            "\n[[body]]\nname = \"die\"",
        );
        assert_eq!(out, expected);
        let names: Vec<String> = world(&out).bodies.into_iter().map(|b| b.name).collect();
        assert_eq!(names, ["crate", "plank", "die", "slab"]);
    }

    #[test]
    fn remove_takes_the_comment_above_the_header_and_keeps_a_detached_one() {
        // TUMBLE's comment sits right above the first body: it is that body's, and goes.
        let text = builtin::TUMBLE;
        let out = edit(text, &[remove("crate")]);
        let expected = cut(
            text,
            "\n# All boxes are thrown",
            "\n[[body]]\nname = \"plank\"",
        );
        assert_eq!(out, expected);

        // A paragraph separated by a blank line heads the section: it stays, before what follows.
        let text = "name = \"s\"\n\n[[material]]\nname = \"m\"\n\n# Section: the drop.\n\n# The ball.\n[[body]]\nname = \"ball\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"m\"\n\n[[body]]\nname = \"die\"\nshape = \"box\"\nsize = [0.1, 0.1, 0.1]\nmaterial = \"m\"\n";
        let out = edit(text, &[remove("ball")]);
        assert_eq!(
            out,
            "name = \"s\"\n\n[[material]]\nname = \"m\"\n\n# Section: the drop.\n\n[[body]]\nname = \"die\"\nshape = \"box\"\nsize = [0.1, 0.1, 0.1]\nmaterial = \"m\"\n"
        );
        // The last body: the paragraph stays at the end.
        let out = edit(text, &[remove("die")]);
        assert!(out.ends_with("material = \"m\"\n"), "{out}");
        let out = edit(&out, &[remove("ball")]);
        assert_eq!(
            out,
            "name = \"s\"\n\n[[material]]\nname = \"m\"\n\n# Section: the drop.\n"
        );
    }

    #[test]
    fn removing_a_generator_removes_its_instances_and_keeps_the_statics() {
        let text = builtin::PACHINKO;
        let out = edit(text, &[remove("ball")]);
        let expected = cut(
            text,
            "\n# The drop: three staggered rows",
            "\n[[body]]\nname = \"ball_high\"",
        );
        assert_eq!(out, expected);
        let w = world(&out);
        assert_eq!(w.bodies.len(), 4); // 2 high balls and 2 dice
        assert_eq!(w.statics, world(text).statics);
    }

    #[test]
    fn removing_any_named_body_of_any_shipped_scene_leaves_a_valid_scene_without_it() {
        for name in builtin::NAMES {
            let text = builtin::get(name).unwrap_or_default();
            let file = format!("scenes/{name}.toml");
            let before = SceneTemplate::parse(text, &file).unwrap_or_else(|e| panic!("{e}"));
            let doc: DocumentMut = text.parse().unwrap_or_else(|e| panic!("{e}"));
            let tables: Vec<&str> = entries(&doc, "body").filter_map(name_of).collect();
            assert!(!tables.is_empty(), "{name}");
            for body in tables {
                let out = apply(text, &file, &[remove(body)]).unwrap_or_else(|e| panic!("{e}"));
                let after = SceneTemplate::parse(&out, &file).unwrap_or_else(|e| panic!("{e}"));
                let made =
                    |n: &str| n == body || n.strip_prefix(body).is_some_and(|r| r.starts_with('['));
                let gone = before.body_names().filter(|n| made(n)).count();
                assert!(gone >= 1, "{name}: {body}");
                assert_eq!(
                    after.body_count(),
                    before.body_count() - gone,
                    "{name}: {body}"
                );
                assert!(
                    !after.body_names().any(made),
                    "{name}: {body} is still there"
                );
                assert_eq!(
                    after.static_count(),
                    before.static_count(),
                    "{name}: {body}"
                );
                // Every other body keeps its table, text for text.
                assert!(out.len() < text.len());
                for line in out.lines() {
                    assert!(text.contains(line), "{name}: new line {line:?}");
                }
            }
        }
    }

    #[test]
    fn a_file_with_crlf_line_ends_keeps_them() {
        let text = builtin::TUMBLE.replace('\n', "\r\n");
        let out = edit(
            &text,
            &[remove("brick"), add(BALL), set("crate.position=[0, 1, 0]")],
        );
        let lf = edit(
            builtin::TUMBLE,
            &[remove("brick"), add(BALL), set("crate.position=[0, 1, 0]")],
        );
        assert_eq!(out, lf.replace('\n', "\r\n"));
    }

    // ---- add ----

    #[test]
    fn add_appends_the_body_after_the_last_one() {
        let text = builtin::TUMBLE;
        let out = edit(text, &[add(BALL)]);
        assert_eq!(
            out,
            format!(
                "{text}\n[[body]]\nname = \"ball\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"wood\"\nposition = [0, 2, 0]\n"
            )
        );
        let w = world(&out);
        let ball = &w.bodies[w.body_index("ball").unwrap_or(usize::MAX)];
        assert_eq!(ball.position, [0.0, 2.0, 0.0]);
        assert_eq!(ball.shape, crate::scene::Shape::Sphere { radius: 0.1 });
        assert_eq!(w.bodies.len(), 6);

        // The same body as `key = value` lines or as a `[[body]]` table gives the same text.
        let lines = "name = \"ball\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"wood\"\nposition = [0, 2, 0]\n";
        assert_eq!(edit(text, &[add(lines)]), out);
        assert_eq!(edit(text, &[add(&format!("[[body]]\n{lines}"))]), out);
    }

    #[test]
    fn an_added_compound_keeps_its_parts_and_goes_before_the_joints() {
        let text = JOINTED;
        let compound = "[[body]]\nname = \"l\"\nshape = \"compound\"\nmaterial = \"m\"\nposition = [1, 1, 0]\n\n[[body.part]]\nshape = \"box\"\nsize = [0.1, 0.5, 0.1]\n\n[[body.part]]\nshape = \"sphere\"\nradius = 0.05\nposition = [0, 0.3, 0]\n";
        let out = edit(text, &[add(compound)]);
        let (before_joint, joint) = out.split_at(out.find("\n# The hinge.").unwrap_or(0));
        assert!(before_joint.ends_with(&format!("\n{compound}")), "{out}");
        assert_eq!(
            joint,
            "\n# The hinge.\n[[joint]]\nname = \"h\"\nkind = \"spherical\"\nbody1 = \"world\"\nbody2 = \"a\"\n"
        );
        let w = world(&out);
        match &w.bodies[1].shape {
            crate::scene::Shape::Compound { parts } => assert_eq!(parts.len(), 2),
            other => panic!("{other:?}"),
        }

        // A scene without bodies gets its first [[body]] table.
        let statics_only = "name = \"e\"\n[[material]]\nname = \"wood\"\n";
        let out = edit(statics_only, &[add(BALL)]);
        assert_eq!(world(&out).bodies.len(), 1);
    }

    #[test]
    fn add_refuses_a_name_in_use() {
        let e = refused(
            builtin::TUMBLE,
            &[add(&BALL.replace("\"ball\"", "\"crate\""))],
        );
        assert!(
            e.starts_with("--add-body crate: a [[body]] named \"crate\" is already in test.toml"),
            "{e}"
        );
        let e = refused(
            builtin::TUMBLE,
            &[add(&BALL.replace("\"ball\"", "\"ground\""))],
        );
        assert!(e.contains("a [[static]] named \"ground\""), "{e}");
        // Twice the same new body: the second is the duplicate.
        let e = refused(builtin::TUMBLE, &[add(BALL), add(BALL)]);
        assert!(e.contains("a [[body]] named \"ball\""), "{e}");
        // After removing it, the name is free.
        let out = edit(
            builtin::TUMBLE,
            &[remove("crate"), add(&BALL.replace("\"ball\"", "\"crate\""))],
        );
        assert_eq!(world(&out).bodies.len(), 5);
    }

    // ---- set ----

    #[test]
    fn set_replaces_one_line_and_the_world_starts_there() {
        let text = builtin::TUMBLE;
        let out = edit(text, &[set("crate.position=[0, 1, 0]")]);
        assert_eq!(
            changed_lines(text, &out),
            [("position = [-1.5, 1.0, 0.0]", "position = [0, 1, 0]")]
        );
        for seed in [0, 1, 99] {
            let w = SceneTemplate::parse(&out, "t.toml").map(|t| t.instantiate(seed));
            let w = w.unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(w.bodies[0].position, [0.0, 1.0, 0.0]);
        }

        // A distribution may replace a number, and the reverse.
        let out = edit(
            text,
            &[
                set("slab.linvel=[0, 0, 0]"),
                set("brick.position=[0, { uniform = [1, 2] }, -1.5]"),
            ],
        );
        assert_eq!(changed_lines(text, &out).len(), 2);
        let w = world(&out);
        assert_eq!(w.bodies[4].linvel, [0.0, 0.0, 0.0]);
        assert!((1.0..=2.0).contains(&w.bodies[2].position[1]));
    }

    #[test]
    fn set_keeps_the_comments_around_the_value() {
        let text = "name = \"s\"\n[[material]]\nname = \"m\"\n[[material]]\nname = \"steel\"\ndensity = 7800\n\n[[body]]\nname = \"ball\"\nshape = \"sphere\"\n# Ten centimetres.\nradius   =   0.1    # keep me\nmaterial = \"m\"\n";
        let out = edit(
            text,
            &[set("ball.radius=0.25"), set("ball.material=\"steel\"")],
        );
        assert_eq!(
            out,
            "name = \"s\"\n[[material]]\nname = \"m\"\n[[material]]\nname = \"steel\"\ndensity = 7800\n\n[[body]]\nname = \"ball\"\nshape = \"sphere\"\n# Ten centimetres.\nradius   =   0.25    # keep me\nmaterial = \"steel\"\n"
        );
        let w = world(&out);
        assert_eq!(
            w.bodies[0].shape,
            crate::scene::Shape::Sphere { radius: 0.25 }
        );
        assert_eq!(w.materials[w.bodies[0].material].name, "steel");
    }

    #[test]
    fn set_adds_a_missing_key_to_the_body() {
        let text = builtin::TUMBLE;
        let out = edit(text, &[set("brick.rotation_deg=[0, 90, 0]")]);
        let expected = text.replace(
            "angvel = [{ uniform = [-8, 8] }, { uniform = [-8, 8] }, { uniform = [-8, 8] }]\n",
            "angvel = [{ uniform = [-8, 8] }, { uniform = [-8, 8] }, { uniform = [-8, 8] }]\nrotation_deg = [0, 90, 0]\n",
        );
        assert_eq!(out, expected);
        let q = world(&out).bodies[2].rotation;
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!(
            (q[1] - h).abs() < 1e-12 && (q[3] - h).abs() < 1e-12,
            "{q:?}"
        );
    }

    #[test]
    fn set_edits_a_generator_and_its_layout() {
        let text = builtin::PACHINKO;
        let out = edit(
            text,
            &[set("ball.row.count=2"), set("die.size=[0.05, 0.05, 0.05]")],
        );
        assert_eq!(
            changed_lines(text, &out),
            [
                (
                    "row = { count = 4, spacing = [0.2, 0, 0] }",
                    "row = { count = 2, spacing = [0.2, 0, 0] }"
                ),
                ("size = [0.06, 0.06, 0.06]", "size = [0.05, 0.05, 0.05]"),
            ]
        );
        let w = world(&out);
        assert_eq!(w.bodies.len(), 6);
        assert!(
            w.bodies
                .iter()
                .filter(|b| b.name.starts_with("die["))
                .all(|b| {
                    b.shape
                        == crate::scene::Shape::Box {
                            half_extents: [0.025; 3],
                        }
                })
        );
        let e = refused(text, &[set("ball.grid.count=[1, 1, 1]")]);
        assert_eq!(
            e,
            "--set ball.grid.count: body \"ball\" has no table `grid` to set `grid.count` in"
        );
    }

    #[test]
    fn edits_apply_in_order_and_only_the_end_result_is_validated() {
        // Halfway, the capsule has no `height`: refused alone, accepted with the next edit.
        let text = "name = \"s\"\n[[material]]\nname = \"m\"\n\n[[body]]\nname = \"ball\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"m\"\n";
        let e = refused(text, &[set("ball.shape=\"capsule\"")]);
        assert!(e.contains("field `height`"), "{e}");
        let out = edit(
            text,
            &[set("ball.shape=\"capsule\""), set("ball.height=0.3")],
        );
        assert_eq!(
            world(&out).bodies[0].shape,
            crate::scene::Shape::Capsule {
                half_height: 0.15,
                radius: 0.1
            }
        );
        let e = refused(
            builtin::TUMBLE,
            &[remove("die"), set("die.position=[0, 1, 0]")],
        );
        assert!(e.starts_with("--set die: no [[body]] named \"die\""), "{e}");
    }

    // ---- refusals ----

    #[test]
    fn every_refusal_names_what_is_wrong() {
        let tumble = builtin::TUMBLE;
        let cases: &[(&str, &[TextEdit], &str)] = &[
            (
                tumble,
                &[remove("crat")],
                "--remove crat: no [[body]] named \"crat\" in test.toml (its [[body]] tables: crate, plank, brick, die, slab)",
            ),
            (
                tumble,
                &[set("crat.radius=1")],
                "--set crat: no [[body]] named \"crat\"",
            ),
            (
                tumble,
                &[remove("ground")],
                "--remove ground: \"ground\" is a [[static]] in test.toml, not a [[body]]: static geometry is not edited in a running job (it needs a new job)",
            ),
            (
                builtin::TOWER,
                &[set("block[1,2,3].position=[0, 0, 0]")],
                "--set block[1,2,3]: body \"block[1,2,3]\" comes from the generator \"block\" (`grid`) in test.toml and has no table of its own: edit the generator (`--set block.FIELD=…`, `--remove block`: all its instances) or give a whole revision file",
            ),
            (
                builtin::PACHINKO,
                &[remove("ball[2]")],
                "body \"ball[2]\" comes from the generator \"ball\" (`row`)",
            ),
            (
                builtin::PACHINKO,
                &[remove("peg_even[0,1,0]")],
                "\"peg_even[0,1,0]\" is a [[static]]",
            ),
            (
                builtin::PACHINKO,
                &[remove("crate[0]")],
                "no [[body]] named \"crate[0]\"",
            ),
            (
                builtin::PACHINKO,
                &[set("ball.radius=-1")],
                "the edited scene is invalid: test.toml:",
            ),
            (
                builtin::PACHINKO,
                &[set("ball.radius=-1")],
                "body \"ball[i]\": field `radius`: must be > 0",
            ),
            (
                tumble,
                &[set("crate.radius=0.1")],
                "body \"crate\": field `radius`: does not apply to shape \"box\"",
            ),
            (
                tumble,
                &[set("crate.possition=[0, 0, 0]")],
                "field `possition`: unknown field (did you mean \"position\"?)",
            ),
            (
                tumble,
                &[set("crate.material=\"steel\"")],
                "field `material`: unknown material \"steel\"",
            ),
            (
                tumble,
                &[set("crate.name=\"plank\"")],
                "duplicate name \"plank\"",
            ),
            (
                tumble,
                &[TextEdit::Set {
                    body: "crate".into(),
                    field: "position".into(),
                    value: "[0, 1".into(),
                }],
                "--set crate.position=[0, 1: the value is not TOML",
            ),
            (
                "name = \"x\"\nbody = [{ name = \"a\", shape = \"sphere\", radius = 1, material = \"m\" }]\n[[material]]\nname = \"m\"\n",
                &[remove("a")],
                "the scene to edit: test.toml:2: scene: field `body`: the bodies are written as array, not as [[body]] tables",
            ),
            (
                "name = \"x\"\n[[body]\n",
                &[remove("a")],
                "the scene to edit: test.toml:2: invalid TOML",
            ),
            (
                "name = \"x\"\n",
                &[remove("a")],
                "(its [[body]] tables: none)",
            ),
            (
                JOINTED,
                &[remove("a")],
                "the edited scene is invalid: test.toml:11: joint \"h\": field `body2`: unknown body \"a\"",
            ),
        ];
        for (text, edits, expected) in cases {
            let e = refused(text, edits);
            assert!(e.contains(expected), "{e}\nexpected: {expected}");
        }
        // A refused scene keeps its structured error.
        match apply(builtin::PACHINKO, "p.toml", &[set("ball.radius=-1")]) {
            Err(TextEditError::Invalid(e)) => {
                assert_eq!(
                    (e.file.as_str(), e.field.as_deref()),
                    ("p.toml", Some("radius"))
                );
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_long_list_of_bodies_is_cut_short_in_a_refusal() {
        let text = builtin::many_bodies(20);
        let e = refused(&text, &[remove("b99")]);
        assert!(
            e.ends_with("(its [[body]] tables: b0, b1, b2, b3, b4, b5, b6, b7, … (20 in all))"),
            "{e}"
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

        /// Whatever position a tumble body is set to, every world starts it there, and every
        /// other line of the file is as it was.
        #[test]
        fn a_set_position_is_where_every_world_starts_the_body(
            which in 0usize..5,
            p in proptest::array::uniform3(-1e3f64..1e3),
            seed in any::<u64>(),
        ) {
            let names = ["crate", "plank", "brick", "die", "slab"];
            let arg = format!("{}.position=[{}, {}, {}]", names[which], p[0], p[1], p[2]);
            let out = apply(builtin::TUMBLE, "t.toml", &[set(&arg)]).map_err(|e| TestCaseError::fail(e.to_string()))?;
            prop_assert_eq!(changed_lines(builtin::TUMBLE, &out).len(), 1);
            let t = SceneTemplate::parse(&out, "t.toml").map_err(|e| TestCaseError::fail(e.to_string()))?;
            prop_assert_eq!(t.instantiate(seed).bodies[which].position, p);
        }
    }
}
