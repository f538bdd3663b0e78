"""MkDocs hooks of the documentation site (mkdocs.yml, ``hooks:``): generate, at build time, what
would otherwise be copied by hand, so that every fact keeps one home.

A page asks for generated Markdown with an HTML comment on a line of its own:

    <!-- sonarset:cli -->                      every command of the typer app (cli/app.py): help, usage, options
    <!-- sonarset:results FILE -->             a benchmark results file: summary, per-dataset tables, timings
    <!-- sonarset:summary FILE -->             only its summary table
    <!-- sonarset:zoo FILE COSTS -->           the model zoo's table (bench/bench_zoo.py's COSTS joined with FILE)
    <!-- sonarset:costs COSTS -->              what each learned method costs to train

FILE and COSTS are paths relative to the repository root; the tables come from
``sonarset.models.benchmark.tables``, the same functions bench/bench_tables.py prints.

Links: a page may link to repository files outside ``docs/`` (``../spec/FORMAT.md``). Those the site
shows (the format spec, the recipes' README, the plugin example's README) are pointed at their page;
any other becomes its path in code, so that ``mkdocs build --strict`` holds for every page.
"""

from __future__ import annotations

import json
import posixpath
import re
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DIRECTIVE = re.compile(r"^<!-- sonarset:(\w+)((?: \S+)*) -->$", re.M)
#: repository files outside docs/ that the site shows, and the page that shows them
SHOWN = {
    "spec/FORMAT.md": "reference/format.md",
    "spec/schema": "reference/schemas.md",
    "recipes/README.md": "reference/recipes.md",
    "examples/sonarset-plugin-example/README.md": "reference/plugin-example.md",
    "examples/sonarset-plugin-example": "reference/plugin-example.md",
}
LINK = re.compile(r"(?<!!)\[([^\]\n]+)\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~)")


# ---------------------------------------------------------------- the command line


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _click():
    """The click that typer's commands are made of: typer 0.2x vendors its own (typer._click)."""
    try:
        from typer import _click as click
    except ImportError:
        import click
    return click


def _param_row(param, ctx) -> str | None:
    if getattr(param, "hidden", False):
        return None
    if param.param_type_name == "argument":
        name = f"`{param.metavar or param.name.upper()}`"
        kind = "argument"
    else:
        name = ", ".join(f"`{n}`" for n in [*param.opts, *param.secondary_opts])
        kind = "flag" if getattr(param, "is_flag", False) else "option"
    if param.multiple or param.nargs == -1:
        kind += ", repeatable"
    typ = param.display_type(ctx).strip("<>")
    default = param.default
    if param.required:
        shown = "required"
    elif default is None or default in ((), "", []) or callable(default):
        shown = ""
    elif isinstance(default, bool) and not param.secondary_opts:
        shown = "on" if default else ""
    elif isinstance(default, bool):
        shown = f"`{param.opts[0] if default else param.secondary_opts[0]}`"
    else:
        shown = f"`{getattr(default, 'value', default)}`"
    return f"| {name} | {kind}: {_cell(typ)} | {shown} | {_cell(param.help or '')} |"


def _subcommands(cmd, ctx) -> list[tuple[str, object]]:
    if not hasattr(cmd, "list_commands"):
        return []
    return [(sub, cmd.get_command(ctx, sub)) for sub in cmd.list_commands(ctx)]


def _command_md(cmd, path: list[str], level: int) -> list[str]:
    click = _click()

    name = " ".join(path)
    ctx = click.Context(cmd, info_name=name)
    lines = [f"{'#' * level} `{name}`", ""]
    if cmd.help:
        lines += [cmd.help.split("\f")[0].strip(), ""]
    subs = _subcommands(cmd, ctx)
    if subs:
        lines += _command_table(name, subs)
        for sub, c in subs:
            lines += _command_md(c, [*path, sub], level + 1)
        return lines
    usage = " ".join(cmd.collect_usage_pieces(ctx))
    lines += ["```text", f"{name} {usage}", "```", ""]
    rows = [r for r in (_param_row(p, ctx) for p in cmd.params if p.name != "help") if r]
    if rows:
        lines += ["| name | kind | default | what |", "| --- | --- | --- | --- |", *rows, ""]
    return lines


def _command_table(name: str, subs) -> list[str]:
    lines = ["| command | what it does |", "| --- | --- |"]
    for sub, c in subs:
        summary = c.short_help or (c.help or "").split("\f")[0].strip().split("\n\n")[0]
        lines.append(f"| [`{name} {sub}`](#{_anchor(name + ' ' + sub)}) | {_cell(summary)} |")
    return [*lines, ""]


def _anchor(title: str) -> str:
    """The id MkDocs' toc extension gives a heading (its default slugify)."""
    slug = re.sub(r"[^\w\s-]", "", title).strip().lower()
    return re.sub(r"[-\s]+", "-", slug)


def cli_markdown() -> str:
    """Every command of the ``sonarset`` typer app, as Markdown: one section per command."""
    import typer.main
    click = _click()

    from sonarset.cli.app import app

    root = typer.main.get_command(app)
    subs = _subcommands(root, click.Context(root, info_name="sonarset"))
    lines = _command_table("sonarset", subs)
    for sub, c in subs:
        lines += _command_md(c, ["sonarset", sub], 2)
    return "\n".join(lines)


# ---------------------------------------------------------------- results tables


def _results(path: str) -> dict:
    from sonarset.models.benchmark import load_results

    return load_results(ROOT / path)


def _json(path: str) -> dict:
    return json.loads((ROOT / path).read_text())


def generated(kind: str, args: list[str]) -> str:
    from sonarset.models.benchmark.tables import cost_table, results_markdown, summary_table, zoo_table

    if kind == "cli":
        return cli_markdown()
    if kind == "results":
        text = results_markdown(_results(args[0]))
        # results.md's own title is the page's; its sections go one level down
        return re.sub(r"^(#+) ", r"#\1 ", re.sub(r"\A# [^\n]*\n", "", text), flags=re.M)
    if kind == "summary":
        return summary_table(_results(args[0]))
    if kind == "zoo":
        return zoo_table(_results(args[0]), _json(args[1]))
    if kind == "costs":
        return cost_table(_json(args[0]))
    raise ValueError(f"unknown directive sonarset:{kind}")


# ---------------------------------------------------------------- links outside docs/


def _outside_links(markdown: str, src_uri: str, docs_dir: Path) -> str:
    page_dir = posixpath.dirname(posixpath.join(docs_dir.relative_to(ROOT).as_posix(), src_uri))

    def fix(m: re.Match) -> str:
        text, target = m.group(1), m.group(2)
        if re.match(r"^[a-z][a-z0-9+.-]*:|^#|^/", target):
            return m.group(0)
        path, _, frag = target.partition("#")
        repo_path = posixpath.normpath(posixpath.join(page_dir, path))
        if repo_path.startswith("docs/") or repo_path == "docs":
            return m.group(0)
        for shown, page in SHOWN.items():
            if repo_path == shown or repo_path.startswith(shown + "/"):
                rel = posixpath.relpath(posixpath.join("docs", page), page_dir)
                return f"[{text}]({rel}{'#' + frag if frag and repo_path == shown else ''})"
        return text if text.startswith("`") else f"{text} (`{repo_path}`)"

    out, fenced = [], False
    for line in markdown.split("\n"):
        if FENCE.match(line.lstrip()):
            fenced = not fenced
        out.append(line if fenced else LINK.sub(fix, line))
    return "\n".join(out)


# ---------------------------------------------------------------- the API's import path

#: where on_config lays out the installed package for mkdocstrings (mkdocs.yml's handler ``paths``)
API_STAGE = ROOT / "build" / "docs-api"


def stage_package() -> None:
    """Lay out the ``sonarset`` package as it installs (pyproject.toml's package-dir: models/ is
    ``sonarset.models``, cli/ is ``sonarset.cli``) under build/docs-api/ (its files copied, its folders linked), where
    mkdocstrings (griffe) finds it: the editable install's import hook maps only the top package."""
    pkg = API_STAGE / "sonarset"
    if pkg.exists():
        shutil.rmtree(pkg)
    pkg.mkdir(parents=True)
    for item in (ROOT / "sonarset").iterdir():
        if item.name in {"models", "cli", "__pycache__"}:
            continue
        if item.is_dir():
            (pkg / item.name).symlink_to(item)
        else:  # a copy: griffe resolves a linked __init__.py to sonarset/ and would scan only that
            shutil.copy2(item, pkg / item.name)
    (pkg / "models").symlink_to(ROOT / "models")
    (pkg / "cli").symlink_to(ROOT / "cli")


# mkdocstrings resolves its handler's paths when the configuration is read, before any event of
# this hook: a path that does not exist yet is dropped, so the layout is made when MkDocs loads
# this module (a fresh clone has no build/ folder).
stage_package()


# ---------------------------------------------------------------- MkDocs events



def on_page_markdown(markdown: str, page, config, files) -> str:
    markdown = DIRECTIVE.sub(lambda m: generated(m.group(1), m.group(2).split()), markdown)
    return _outside_links(markdown, page.file.src_uri, Path(config["docs_dir"]))
