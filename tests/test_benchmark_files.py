"""The benchmark scripts write their runs into Markdown files that also hold text written by hand."""

import importlib.util
from pathlib import Path

_spec = importlib.util.spec_from_file_location(
    "written", Path(__file__).resolve().parents[1] / "benchmarks" / "written.py")
written = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(written)

RUN1 = "# Throughput\n\n- Date: 1\n\n| a | 1 |\n"
RUN2 = "# Throughput\n\n- Date: 2\n\n| a | 2 |\n"


def test_a_run_replaces_the_scripts_earlier_run_and_keeps_everything_else(tmp_path):
    path = tmp_path / "results.md"
    written.write_run(path, RUN1, "bench.py")
    assert path.read_text().startswith("# Throughput\n\n<!-- bench.py:") and "| a | 1 |" in path.read_text()
    path.write_text(path.read_text() + "\n## Why\n\nNotes written by hand.\n")
    written.write_run(path, RUN2, "bench.py")
    text = path.read_text()
    assert "| a | 2 |" in text and "| a | 1 |" not in text and "Date: 1" not in text
    assert text.endswith("## Why\n\nNotes written by hand.\n") and text.count("# Throughput") == 1
    written.write_run(path, RUN1, "other.py")  # another script's run: above, the first one's kept
    text = path.read_text()
    assert text.index("| a | 1 |") < text.index("| a | 2 |") < text.index("Notes written by hand.")
    assert not [p.name for p in tmp_path.iterdir() if p.name != "results.md"]  # no temporary file left


def test_a_history_keeps_every_run_newest_first_and_a_file_without_runs_whole(tmp_path):
    path = tmp_path / "compile.md"
    path.write_text("# Compile time\n\n## An analysis\n\nWritten by hand.\n")
    written.write_run(path, RUN1, "bench.py", keep_earlier=True)
    written.write_run(path, RUN2, "bench.py", keep_earlier=True)
    text = path.read_text()
    assert text.startswith("# Compile time\n\n<!-- bench.py:") and "# Throughput" not in text
    assert text.index("| a | 2 |") < text.index("| a | 1 |") < text.index("## An analysis\n\nWritten by hand.\n")
    untitled = tmp_path / "notes.md"
    untitled.write_text("Written by hand, no title.\n")
    written.write_run(untitled, RUN1, "bench.py")
    assert untitled.read_text().startswith("# Throughput\n\n") and untitled.read_text().endswith(
        "Written by hand, no title.\n")
