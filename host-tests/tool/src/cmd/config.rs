//! `tinybms config`: the bridge's own configuration: show, change (one-way changes ask), save to a file and load it back (the secrets it cannot restore named).

use std::path::Path;

use tinybms_firmware::config::value::Parsed;
use tinybms_firmware::config::{Config, FieldId};

use crate::cli::Conn;
use crate::client::Client;
use crate::config::Shown;
use crate::{config, confirm, connect, monitor, ToolError, ToolResult};

/// `tinybms config …` (see [`config`]).
pub fn run_config(
    conn: &Conn,
    args: &[String],
    save: Option<&Path>,
    load: Option<&Path>,
    dry_run: bool,
    reset: bool,
    yes: bool,
) -> ToolResult<()> {
    // Everything that can be checked without the bridge is checked first.
    let assignments = check_arguments(conn, args, load, dry_run)?;
    let explain = match (&assignments, args.first()) {
        (None, Some(name)) => Some(config::field_named(name)?),
        _ => None,
    };
    let loaded = load.map(read_file).transpose()?;
    if reset
        && !yes
        && !confirm("Set every field of the bridge's configuration back to its default")?
    {
        return Err(ToolError::failed("not confirmed: nothing changed"));
    }
    let mut c = connect(conn)?;
    config::require_bridge(&c)?;
    let (fields, end) = config::fetch(&mut c).map_err(config::fetch_error)?;
    let current = config::record_of(&fields);
    if let Some(changes) = assignments {
        config::check_locally(&current, &changes)?;
        if dry_run {
            // Checked by the firmware's rules (each field, and the fields
            // against each other): what would be written.
            print_changes(&fields, &changes);
            println!("dry run: checked, nothing changed");
            return Ok(());
        }
        confirm_one_way(yes, &current, &changes)?;
        return config::apply(&mut c, &changes);
    }
    if let (Some(path), Some(file)) = (load, loaded) {
        let to = Target {
            fields: &fields,
            current: &current,
        };
        return apply_file(&mut c, to, path, file, dry_run, yes);
    }
    if reset {
        return config::reset(&mut c, &fields);
    }
    if let Some(id) = explain {
        let f = fields
            .iter()
            .find(|f| f.name == id.name())
            .ok_or_else(|| ToolError::failed(format!("the bridge has no field `{}`", id.name())))?;
        print!("{}", config::render_one(f));
        return Ok(());
    }
    if let Some(path) = save {
        return save_file(&c.port, &fields, path);
    }
    print!("{}", config::render(&fields, &end));
    Ok(())
}

/// The arguments, checked before the bridge is asked anything: the changes
/// they give (`NAME=VALUE...`), if any.
fn check_arguments(
    conn: &Conn,
    args: &[String],
    load: Option<&Path>,
    dry_run: bool,
) -> ToolResult<Option<Vec<(FieldId, Parsed)>>> {
    // Arguments in the wrong order: the port comes first.
    let looks_like_port = |a: &str| {
        a.starts_with("/dev/")
            || a.starts_with("\\\\.\\")
            || (a.len() > 3
                && a[..3].eq_ignore_ascii_case("com")
                && a[3..].bytes().all(|b| b.is_ascii_digit()))
    };
    if conn.port.contains('=') || args.iter().any(|a| looks_like_port(a)) {
        return Err(ToolError::usage(format!(
            "the port comes first: tinybms config PORT NAME=VALUE... (`{}` is not a port)",
            conn.port
        )));
    }
    let assignments = if args.iter().any(|x| x.contains('=')) {
        let mut out = Vec::new();
        for arg in args {
            let (name, text) = config::split_assignment(arg)?;
            let (id, p) = config::check_assignment(&name, &text)?;
            if out.iter().any(|(o, _)| *o == id) {
                return Err(ToolError::usage(format!(
                    "`{}` is given twice: give each field once",
                    id.name()
                )));
            }
            out.push((id, p));
        }
        Some(out)
    } else {
        None
    };
    if assignments.is_none() && args.len() > 1 {
        return Err(ToolError::usage(
            "tinybms config PORT NAME (one field), or NAME=VALUE... to change fields",
        ));
    }
    if dry_run && load.is_none() && assignments.is_none() {
        return Err(ToolError::usage("--dry-run goes with --load or NAME=VALUE"));
    }
    Ok(assignments)
}

/// A saved configuration: its record, and the secrets the saved bridge had
/// set (the file names them, without values).
struct SavedFile {
    record: Vec<(FieldId, Parsed)>,
    secrets: Vec<String>,
}

fn read_file(path: &Path) -> ToolResult<SavedFile> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| ToolError::failed(format!("cannot read `{}`: {e}", path.display())))?;
    let secrets = text
        .lines()
        .filter_map(|l| l.strip_prefix("# "))
        .filter_map(|l| l.strip_suffix(": set (secrets are not saved)"))
        .map(str::to_string)
        .collect();
    let record = config::parse_file(&text)
        .map_err(|e| ToolError::failed(format!("{}: {e}", path.display())))?;
    Ok(SavedFile { record, secrets })
}

/// The bridge's configuration as it answered.
struct Target<'a> {
    fields: &'a [Shown],
    current: &'a Config,
}

/// `--load FILE`: the fields that differ from the bridge's, applied (or only
/// shown with `--dry-run`); the secrets the file could not carry, named.
fn apply_file(
    c: &mut Client,
    to: Target<'_>,
    path: &Path,
    file: SavedFile,
    dry_run: bool,
    yes: bool,
) -> ToolResult<()> {
    let (fields, current) = (to.fields, to.current);
    let mut changes = config::diff(current, &file.record);
    // A bridge without Wi-Fi refuses the network fields: they stay out, said.
    if !c.hello.features.iter().any(|f| f == "wifi") {
        let (network, rest): (Vec<_>, Vec<_>) = changes
            .into_iter()
            .partition(|(id, _)| id.field().group == tinybms_firmware::config::Group::Network);
        if !network.is_empty() {
            let names: Vec<&str> = network.iter().map(|(id, _)| id.name()).collect();
            println!(
                "skipped: {} (this image has no Wi-Fi; the images with Wi-Fi end in -wifi)",
                names.join(", ")
            );
        }
        changes = rest;
    }
    config::check_locally(current, &changes)?;
    println!(
        "{}: {} fields, {} differ from the bridge's",
        path.display(),
        file.record.len(),
        changes.len()
    );
    print_changes(fields, &changes);
    // Secrets are never in a file: say which the bridge now lacks, and how.
    let missing: Vec<&String> = file
        .secrets
        .iter()
        .filter(|name| {
            fields
                .iter()
                .any(|f| f.name == **name && f.value == "unset")
        })
        .collect();
    let say_missing = || {
        if !missing.is_empty() {
            let names: Vec<&str> = missing.iter().map(|s| s.as_str()).collect();
            println!(
                "not restored: {} (secrets are never saved in a file). Set {} again: {}",
                names.join(", "),
                if names.len() == 1 { "it" } else { "them" },
                secrets_hint(&names)
            );
        }
    };
    if dry_run || changes.is_empty() {
        if dry_run {
            println!("dry run: nothing changed");
        }
        say_missing();
        return Ok(());
    }
    confirm_one_way(yes, current, &changes)?;
    config::apply(c, &changes)?;
    say_missing();
    Ok(())
}

/// `--save FILE`: every field but the secrets, with a header saying whence.
fn save_file(port: &str, fields: &[Shown], path: &Path) -> ToolResult<()> {
    let header = format!(
        "saved by tinybms {} from {} at {}",
        env!("CARGO_PKG_VERSION"),
        port,
        monitor::utc_now()
    );
    std::fs::write(path, config::file_text(fields, &header))
        .map_err(|e| ToolError::failed(format!("cannot write `{}`: {e}", path.display())))?;
    let secrets = fields.iter().filter(|f| f.secret).count();
    println!(
        "saved {} fields to {} ({secrets} secrets left out)",
        fields.len() - secrets,
        path.display()
    );
    Ok(())
}

/// The commands that set the secrets `names` again.
pub fn secrets_hint(names: &[&str]) -> String {
    let mut out = Vec::new();
    if names.contains(&"wifi_key") {
        out.push("`tinybms wifi PORT --ssid NAME` (asks for the passphrase)");
    }
    if names.contains(&"mqtt_password") {
        out.push("`tinybms mqtt PORT --host HOST --user USER` (asks for the password)");
    }
    if out.is_empty() {
        out.push("`tinybms config PORT NAME=VALUE`");
    }
    out.join(" and ")
}
/// A change that nothing over the host link can undo (`read_only=on`: from
/// then on the bridge refuses every change, this one's undoing included) is
/// made only when confirmed (or `--yes`), like `reset`.
pub fn confirm_one_way(
    yes: bool,
    current: &tinybms_firmware::config::Config,
    changes: &[(
        tinybms_firmware::config::FieldId,
        tinybms_firmware::config::value::Parsed,
    )],
) -> ToolResult<()> {
    use tinybms_firmware::config::value::Parsed;
    use tinybms_firmware::config::FieldId;
    let locks = !current.read_only
        && changes
            .iter()
            .any(|(id, p)| *id == FieldId::ReadOnly && *p == Parsed::Bool(true));
    if !locks || yes {
        return Ok(());
    }
    let question = "read_only=on is one-way: from then on the bridge refuses every change \
                    over USB, turning it off included; only the BOOT button held 5 s while the \
                    bridge runs (or erasing the flash) lifts it. Turn it on";
    if confirm(question)? {
        Ok(())
    } else {
        Err(ToolError::failed("not confirmed: nothing changed"))
    }
}

/// Each change as `name  now -> new`, the new value in the firmware's words.
fn print_changes(
    fields: &[config::Shown],
    changes: &[(
        tinybms_firmware::config::FieldId,
        tinybms_firmware::config::value::Parsed,
    )],
) {
    for (id, p) in changes {
        let mut l = tinybms_firmware::text::Line::new();
        tinybms_firmware::config::value::write(id.field(), &p.as_value(), true, &mut l);
        let now = fields
            .iter()
            .find(|f| f.name == id.name())
            .map_or("?", |f| f.value.as_str());
        println!("  {:<24} {now} -> {}", id.name(), l.as_str());
    }
}
