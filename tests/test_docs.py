"""The documentation: the site builds with no broken link or missing page, its reference of the
kinds is what the declarations say, and every Python, shell and TOML snippet of it (and of the
README) runs as written, with small run counts."""

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from test_cli import _command

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(DOCS.glob("*.md")) + [ROOT / "README.md"]


def _blocks(page: Path, language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```", page.read_text(), re.S | re.M)


def _where(tmp_path) -> Path:
    """A folder to run snippets in, with the bundled experiments where the docs say they are."""
    (tmp_path / "experiments").symlink_to(ROOT / "experiments")
    return tmp_path


def test_the_site_builds_strictly_and_the_kinds_reference_is_the_declarations(tmp_path):
    pytest.importorskip("mkdocs", reason="the docs extra (pip install -e '.[docs]')")
    from tracklab.config.reference import kinds_markdown

    assert (DOCS / "kinds.md").read_text() == kinds_markdown(), \
        "docs/kinds.md is not what the declarations say: tracklab list --markdown > docs/kinds.md"
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "site" / "api" / "index.html").read_text().count("run_filter") > 2  # the API reference
    for page in ("getting-started", "kinds", "clutter", "papers", "mathematics", "gallery"):
        assert (tmp_path / "site" / page / "index.html").is_file(), page


# the own filter's page example runs in tests/test_own_filter.py (with what it prints checked)
PYTHON = [p for p in PAGES if _blocks(p, "python") and p.name != "own-filter.md"]


@pytest.mark.parametrize("page", PYTHON, ids=lambda p: p.name)
def test_the_python_snippets_run(tmp_path, page):
    """A page's Python snippets, in order, as one program (a page reads top to bottom)."""
    code = "\n".join(_blocks(page, "python"))
    (tmp_path / "snippets.py").write_text(code)
    out = subprocess.run([sys.executable, "snippets.py"], cwd=_where(tmp_path), capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]


def test_the_toml_snippets_are_experiment_files_and_the_shell_snippets_run(tmp_path):
    """Every TOML snippet is a valid experiment file (the getting-started one runs); every
    `tracklab` line of a shell snippet runs, with 200 runs and no figures (pip lines are what
    installing does)."""
    from tracklab.config import load_experiment

    where = _where(tmp_path)
    for page in PAGES:
        for i, text in enumerate(_blocks(page, "toml")):
            path = where / f"{page.stem}_{i}.toml"
            path.write_text(text)
            load_experiment(path)  # a bad snippet raises ConfigError, naming its field
            if page.name == "getting-started.md":
                (where / "first.toml").write_text(text)
    commands = []
    for page in PAGES:
        for text in _blocks(page, "bash"):
            for line in text.splitlines():
                line = line.split(" #")[0].strip()
                if line.startswith("pip "):
                    continue
                for part in line.split("&&"):
                    part = part.strip()
                    if part.startswith("tracklab ") and part not in commands:
                        commands.append(part)
    assert commands, "no tracklab command in the docs' shell snippets"
    for i, command in enumerate(commands):
        args = shlex.split(command)[1:]
        if args[0] in ("run", "sweep"):
            args += ["--runs", "200", "--no-figures", "--out", str(where / f"out{i}")]
        if args[0] == "plot":  # the results folders it names are the repository's, as reproduce wrote them
            for folder in (a for a in args[1:] if a.startswith("results/")):
                shutil.copytree(ROOT / folder, where / folder)
        out = subprocess.run([*_command(), *args], cwd=where, capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, (command, out.stderr[-3000:])
