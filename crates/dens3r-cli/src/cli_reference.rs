//! `dens3r cli-reference` (hidden): the full command-line reference as Markdown, from clap's
//! own help, so `docs/cli.md` cannot drift from the code (`scripts/gen-cli-docs.sh` writes it;
//! a test compares).

use clap::Command;

/// The reference of `root` and every visible subcommand below it, depth first.
pub fn markdown(root: &Command) -> String {
    let mut out = String::from(
        "# Command-line reference\n\nGenerated from the commands' own help by `scripts/gen-cli-docs.sh` \
         (`dens3r cli-reference`); a test fails when it is out of date.\n",
    );
    section(root, root.get_name(), &mut out);
    out
}

fn section(cmd: &Command, path: &str, out: &mut String) {
    let mut cmd = cmd.clone().bin_name(path).disable_colored_help(true);
    let help = cmd.render_long_help().to_string();
    let help: Vec<&str> = help.lines().map(str::trim_end).collect();
    out.push_str(&format!("\n## `{path}`\n\n```text\n{}\n```\n", help.join("\n").trim_end()));
    for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set() && s.get_name() != "help") {
        section(sub, &format!("{path} {}", sub.get_name()), out);
    }
}
