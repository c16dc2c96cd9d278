//! The command-line reference: every flag, environment variable and subcommand of each binary,
//! read from its `clap` definition.

use anyhow::Result;
use clap::{Arg, Command, CommandFactory as _};
use serde_json::Value;

use crate::md;

/// One page per binary (the two simulators share one): `(file name, Markdown)`.
pub fn pages() -> Result<Vec<(String, String)>> {
    let operator = page(
        "lekiwi-operator",
        "The operator: controllers and the agent gateway in one binary. Every flag can also be \
         set by the environment variable shown.",
        &[lekiwi_operator::config::Config::command()],
        None,
    );
    let agent = page(
        "lekiwi-agent",
        "The robot agent. Every setting is a key of the configuration file \
         (`/etc/lekiwi/agent.yaml`, camelCase), a flag and an environment variable; a flag wins \
         over the environment, the environment over the file, the file over the default.",
        &[lekiwi_agent::config::Flags::command()],
        Some(&agent_keys()?),
    );
    let cli = page(
        "kubectl-lekiwi",
        "The kubectl plugin: with `kubectl-lekiwi` on the `PATH`, `kubectl lekiwi`. The options \
         of the first table apply to every command.",
        &[kubectl_lekiwi::Cli::command()],
        None,
    );
    let sims = page(
        "Fleet simulators",
        "`lekiwi-fleet` runs many real agents (the agent's own code, one state directory each) in \
         one process; `lekiwi-sim` opens many light agent connections for load tests.",
        &[
            lekiwi_agent::fleet::Args::command(),
            lekiwi_agent::sim::Args::command(),
        ],
        None,
    );
    Ok(vec![
        ("lekiwi-operator.md".into(), operator),
        ("lekiwi-agent.md".into(), agent),
        ("kubectl-lekiwi.md".into(), cli),
        ("simulators.md".into(), sims),
    ])
}

/// The agent's configuration file keys, each with its default: `(key, default)`.
type Keys = Vec<(String, Value)>;

fn agent_keys() -> Result<Keys> {
    let defaults = serde_json::to_value(lekiwi_agent::config::Config::default())?;
    let mut keys: Keys = defaults
        .as_object()
        .map(|o| o.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
        .unwrap_or_default();
    // The token itself is never printed, so it is not serialized; it is a key all the same.
    keys.push(("enrollmentToken".into(), Value::Null));
    Ok(keys)
}

fn page(title: &str, intro: &str, commands: &[Command], keys: Option<&Keys>) -> String {
    let mut out = md::generated_note("the binaries' `clap` definitions");
    out.push_str(&format!("# {title}\n\n{intro}\n\n"));
    for cmd in commands {
        let mut cmd = cmd.clone();
        cmd.build();
        let heading = if commands.len() > 1 { "##" } else { "" };
        section(&cmd, &[], heading, keys, &mut out);
    }
    out
}

/// `cmd` (reached by `path` from its binary), then each of its subcommands.
fn section(cmd: &Command, path: &[&str], heading: &str, keys: Option<&Keys>, out: &mut String) {
    // A built command's bin name is its whole path (`kubectl lekiwi robot add`).
    let name = cmd.get_bin_name().unwrap_or(cmd.get_name());
    if !heading.is_empty() {
        out.push_str(&format!("{heading} `{name}`\n\n"));
    }
    if let Some(about) = cmd.get_long_about().or(cmd.get_about()) {
        out.push_str(&md::cell(&about.to_string()));
        out.push_str("\n\n");
    }
    out.push_str(&format!("```text\n{}\n```\n\n", usage(cmd)));
    let args: Vec<&Arg> = cmd
        .get_arguments()
        .filter(|a| !a.is_hide_set() && !matches!(a.get_id().as_str(), "help" | "version"))
        .filter(|a| path.is_empty() || !a.is_global_set())
        .collect();
    if !args.is_empty() {
        out.push_str(&arg_table(&args, keys));
        out.push('\n');
    }
    if let Some(after) = cmd.get_after_long_help().or(cmd.get_after_help()) {
        out.push_str(&md::cell(&after.to_string()));
        out.push_str("\n\n");
    }
    let deeper = if heading.is_empty() { "##" } else { "###" };
    for sub in cmd.get_subcommands().filter(|s| s.get_name() != "help") {
        let mut sub_path = path.to_vec();
        sub_path.push(sub.get_name());
        section(sub, &sub_path, deeper, None, out);
    }
}

/// The usage line as `--help` prints it, without its `Usage:` prefix.
fn usage(cmd: &Command) -> String {
    let text = cmd.clone().render_usage().to_string();
    text.trim_start_matches("Usage:").trim().to_owned()
}

fn arg_table(args: &[&Arg], keys: Option<&Keys>) -> String {
    let rows: Vec<Vec<String>> = args
        .iter()
        .map(|arg| {
            let key = keys.and_then(|k| key_of(arg, k));
            let mut row = Vec::new();
            if keys.is_some() {
                row.push(key.map(|(k, _)| md::code(k)).unwrap_or_else(|| "—".into()));
            }
            row.push(flag(arg));
            row.push(
                arg.get_env()
                    .map(|e| md::code(&e.to_string_lossy()))
                    .unwrap_or_else(|| "—".into()),
            );
            row.push(default(arg, key.map(|(_, v)| v)));
            row.push(md::cell(&help(arg)));
            row
        })
        .collect();
    let header: &[&str] = if keys.is_some() {
        &["File key", "Flag", "Environment", "Default", "Description"]
    } else {
        &["Flag", "Environment", "Default", "Description"]
    };
    md::table(header, &rows)
}

/// The configuration file key of `arg`: its long name in camelCase, when that is a key.
fn key_of<'a>(arg: &Arg, keys: &'a Keys) -> Option<&'a (String, Value)> {
    let long = arg.get_long()?;
    let mut camel = String::new();
    let mut upper = false;
    for c in long.chars() {
        match c {
            '-' => upper = true,
            c if upper => {
                camel.push(c.to_ascii_uppercase());
                upper = false;
            }
            c => camel.push(c),
        }
    }
    keys.iter().find(|(k, _)| *k == camel)
}

/// `--long <VALUE>, -s`, or `<NAME>` for a positional argument.
fn flag(arg: &Arg) -> String {
    let value = arg
        .get_value_names()
        .map(|v| {
            v.iter()
                .map(|n| format!("<{n}>"))
                .collect::<Vec<_>>()
                .join(" ")
        })
        .unwrap_or_else(|| format!("<{}>", arg.get_id().as_str().to_ascii_uppercase()));
    let num = arg.get_num_args();
    let takes_value = num.is_none_or(|n| n.takes_values());
    let value = if num.is_some_and(|n| n.min_values() == 0) {
        format!("[{value}]")
    } else {
        value
    };
    let mut names = Vec::new();
    if let Some(long) = arg.get_long() {
        names.push(if takes_value && arg.get_action().takes_values() {
            md::code(&format!("--{long} {value}"))
        } else {
            md::code(&format!("--{long}"))
        });
    }
    if let Some(short) = arg.get_short() {
        names.push(md::code(&format!("-{short}")));
    }
    if names.is_empty() {
        names.push(md::code(&value));
    }
    names.join(", ")
}

fn default(arg: &Arg, key_default: Option<&Value>) -> String {
    let clap_default: Vec<String> = arg
        .get_default_values()
        .iter()
        .map(|v| v.to_string_lossy().into_owned())
        .collect();
    if !clap_default.is_empty() {
        return md::code(&clap_default.join(","));
    }
    match key_default {
        Some(Value::String(s)) if !s.is_empty() => md::code(s),
        Some(Value::Array(a)) if !a.is_empty() => md::code(
            &a.iter()
                .map(|v| v.as_str().map_or_else(|| v.to_string(), str::to_owned))
                .collect::<Vec<_>>()
                .join(","),
        ),
        Some(v @ (Value::Number(_) | Value::Bool(_))) => md::code(&v.to_string()),
        _ => "—".into(),
    }
}

/// The long help (or the help), then the values it takes.
fn help(arg: &Arg) -> String {
    let mut text = arg
        .get_long_help()
        .or(arg.get_help())
        .map(|h| h.to_string())
        .unwrap_or_default();
    let values: Vec<String> = arg
        .get_possible_values()
        .iter()
        .filter(|v| !v.is_hide_set())
        .map(|v| match v.get_help() {
            Some(h) => format!(
                "`{}`: {}",
                v.get_name(),
                h.to_string().trim_end_matches('.')
            ),
            None => format!("`{}`", v.get_name()),
        })
        .collect();
    let is_bool = values.len() == 2 && values.iter().all(|v| v == "`true`" || v == "`false`");
    if !values.is_empty() && !is_bool {
        if !text.is_empty() && !text.ends_with('.') {
            text.push('.');
        }
        text.push_str(&format!(" Values: {}.", values.join("; ")));
    }
    if arg.is_required_set() {
        text.push_str(" Required.");
    }
    text
}
