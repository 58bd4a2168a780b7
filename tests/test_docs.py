"""The docs name what ships: every study file and ``ocv2 study`` option in docs/studies.md, every module, bench
script and docs page in the README's repository map. A file added without its line fails here."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from cluster.cli import study as study_cli

ROOT = Path(__file__).resolve().parents[1]


def section(markdown: str, heading: str) -> str:
    """The text under ``heading`` (a ``## `` line) up to the next heading of that level."""
    start = markdown.index(f"\n## {heading}\n")
    end = markdown.find("\n## ", start + 1)
    return markdown[start : None if end < 0 else end]


def test_studies_doc_lists_every_shipped_study():
    shipped = section((ROOT / "docs" / "studies.md").read_text(), "Shipped studies (`configs/studies/`)")
    # Table rows name files, or a family of them: `table1_<layout>.yaml`, `table2_test_time_{simple,wide}_as_run.yaml`.
    patterns = []
    for name in re.findall(r"`([\w<>{},]+\.yaml)`", shipped):
        pattern = re.escape(name).replace("<layout>", r"[a-z_]+")
        pattern = re.sub(r"\\\{([\w,]+)\\\}", lambda m: "(" + m.group(1).replace(",", "|") + ")", pattern)
        patterns.append(re.compile(pattern))
    files = sorted(path.name for path in (ROOT / "configs" / "studies").glob("*.yaml"))
    assert files
    missing = [name for name in files if not any(p.fullmatch(name) for p in patterns)]
    assert not missing, f"docs/studies.md, 'Shipped studies': no row for {missing}"


def test_studies_doc_names_every_study_command_and_option():
    doc = (ROOT / "docs" / "studies.md").read_text()
    parser = study_cli.add_parser(argparse.ArgumentParser().add_subparsers())
    (commands,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    missing = [f"ocv2 study {name}" for name in commands.choices if f"ocv2 study {name}" not in doc]
    for name, command in commands.choices.items():
        for action in command._actions:
            missing += [
                f"{name} {flag}"
                for flag in action.option_strings
                if flag.startswith("--") and flag != "--help" and flag not in doc
            ]
    assert not missing, f"docs/studies.md does not mention {missing}"


def test_readme_map_names_every_module_script_and_docs_page():
    readme = (ROOT / "README.md").read_text()
    repository_map = section(readme, "Repository map")
    files = [
        *(p for package in ("ocv2", "population") for p in (ROOT / package).glob("*.py") if p.name != "__init__.py"),
        *(p for p in (ROOT / "bench").iterdir() if p.suffix in (".py", ".sh")),
        *(ROOT / "docs").glob("*.md"),
    ]
    missing = sorted(str(p.relative_to(ROOT)) for p in files if f"`{p.name}`" not in repository_map)
    assert not missing, f"README's repository map does not name {missing}"
    assert "`CHANGELOG.md`" in repository_map and (ROOT / "CHANGELOG.md").is_file()


def test_results_index_names_every_results_folder():
    index = (ROOT / "docs" / "results" / "README.md").read_text()
    folders = sorted(p.name for p in (ROOT / "docs" / "results").iterdir() if p.is_dir() and p.name != "__pycache__")
    missing = [name for name in folders if f"[{name}/]({name}/" not in index]
    assert not missing, f"docs/results/README.md does not list {missing}"


def test_every_test_the_docs_name_exists():
    """docs/extending.md once told readers to copy a test that had been renamed: a named test must be in its file."""
    named = {
        (match[1], match[2])
        for page in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]
        for match in re.finditer(r"tests/(test_\w+\.py)::(\w+)", page.read_text())
    }
    assert len(named) > 10  # the pattern still finds what the docs name
    missing = [
        f"tests/{file}::{name}"
        for file, name in sorted(named)
        if not re.search(rf"^\s*(?:async )?(?:def|class) {name}\b", _text(ROOT / "tests" / file), re.MULTILINE)
    ]
    assert not missing, f"the docs name tests that do not exist: {missing}"


def _text(path: Path) -> str:
    return path.read_text() if path.is_file() else ""
