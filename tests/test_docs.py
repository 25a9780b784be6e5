"""The user docs stay short, linked and current; numbers live in benchmark records, history in git.

README.md is for users (what it does, how to run it, what comes out); depth goes to docs/*.md, and every measured
number comes from a record under benchmarks/results/ that says which commit, machine and load produced it. Code
docstrings and comments say what and why, never when or at which commit.
"""
from __future__ import annotations

import ast
import io
import json
import re
import shlex
import tokenize
from pathlib import Path

import pytest

from recon.app.bench import provenance, provenance_lines

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
MAX_README_LINES = 300

MARKDOWN_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
HTML_SOURCE = re.compile(r"<(?:img|a)\b[^>]*\b(?:src|href)=\"([^\"]+)\"", re.IGNORECASE)
DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
COMMIT_HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b")
RECORD_KEYS = ("commit", "machine", "date", "load_average_start")
TRAINING_KEYS = ("steps", "rays_per_s", "psnr")
"""A row that trained a field (it has any of these) has all three: what it did in its time and how good it got."""


def doc_pages() -> list[Path]:
    return [README, *sorted((REPO / "docs").glob("*.md")), REPO / "benchmarks" / "README.md"]


def relative_targets(text: str) -> list[str]:
    """Link and image targets that point into the repository (not web addresses or in-page anchors)."""
    targets = MARKDOWN_LINK.findall(text) + HTML_SOURCE.findall(text)
    return [t.split("#")[0] for t in targets if not re.match(r"^[a-z][a-z0-9+.-]*:", t) and not t.startswith("#")]


def prose(source: str) -> list[tuple[int, str]]:
    """(line, text) of a module's comments and docstrings (module, class, function and attribute strings)."""
    found = [(tok.start[0], tok.string) for tok in tokenize.generate_tokens(io.StringIO(source).readline)
             if tok.type == tokenize.COMMENT]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            found.append((node.lineno, node.value.value))
    return found


def test_readme_is_short_enough_to_read() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines; move depth to a page under docs/"


@pytest.mark.parametrize("page", doc_pages(), ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_and_image_exists(page: Path) -> None:
    assert page.exists(), f"{page.relative_to(REPO)} is missing"
    missing = [t for t in relative_targets(page.read_text()) if t and not (page.parent / t).exists()]
    assert not missing, f"{page.relative_to(REPO)} links to missing files: {missing}"


def test_link_finder_sees_markdown_and_html_links() -> None:
    text = '![a](docs/x.png) [b](docs/y.md#part) <img src="docs/z.png" width="3"> [w](https://a.org/b) [c](#top)'
    assert relative_targets(text) == ["docs/x.png", "docs/y.md", "docs/z.png"]


def test_code_prose_has_no_dates_or_commit_hashes() -> None:
    """When and at which commit something was measured belongs to git and the benchmark records."""
    offenders = []
    for path in sorted((REPO / "recon").rglob("*.py")):
        for line, text in prose(path.read_text()):
            for pattern in (DATE, COMMIT_HASH):
                for match in pattern.finditer(text):
                    offenders.append(f"{path.relative_to(REPO)}:{line}: {match.group(0)}")
    for path in sorted((REPO / "pipelines").glob("*.toml")):  # the presets' comments
        for line, text in enumerate(path.read_text().splitlines(), 1):
            comment = text.partition("#")[2]
            offenders += [f"{path.relative_to(REPO)}:{line}: {m.group(0)}"
                          for pattern in (DATE, COMMIT_HASH) for m in pattern.finditer(comment)]
    assert not offenders, "dates or commit hashes in code prose:\n" + "\n".join(offenders)


def test_prose_patterns_catch_dates_and_hashes_but_not_numbers() -> None:
    source = '"""Measured 2026-11-24 at fd6d232."""\nX = 1  # 0.28209479177387814, 2654435761, decade\n'
    texts = " ".join(text for _, text in prose(source))
    assert DATE.findall(texts) == ["2026-11-24"]
    assert COMMIT_HASH.findall(texts) == ["fd6d232"]


def test_ci_runs_the_readme_test_command() -> None:
    """.ci/run installs and tests exactly as the README tells a user to (it may add flags such as -q)."""
    blocks = re.findall(r"```bash\n(.*?)```", README.read_text(), re.DOTALL)
    command = next(line for block in blocks for line in block.splitlines() if "python -m pytest" in line)
    ci_lines = [shlex.split(line) for line in (REPO / ".ci" / "run").read_text().splitlines()
                if line.strip() and not line.lstrip().startswith("#")]

    def runs(words: list[str]) -> bool:  # some .ci/run line holds these words in this order
        for ci in ci_lines:
            rest = iter(ci)
            if all(word in rest for word in words):
                return True
        return False

    parts = [shlex.split(part) for part in command.split("&&")]
    assert parts[0][:2] == ["pip", "install"] and parts[-1][:3] == ["python", "-m", "pytest"]
    assert all(runs(part) for part in parts), f".ci/run does not run the README's test command: {command}"


def test_readme_quickstart_is_runnable_as_written() -> None:
    text = README.read_text()
    assert "pip install -c constraints.txt -e . && recon run fixtures/sample/images --out scene --preset fast" in text
    assert (REPO / "fixtures" / "sample" / "images").is_dir() and (REPO / "pipelines" / "fast.toml").exists()


def test_every_benchmark_record_says_where_it_ran_and_is_listed() -> None:
    listing = (REPO / "benchmarks" / "README.md").read_text()
    records = sorted((REPO / "benchmarks" / "results").glob("*.json"))
    assert records, "no benchmark records: the docs' numbers must come from one"
    for record in records:
        assert f"results/{record.name}" in listing, f"benchmarks/README.md does not say which command wrote {record.name}"
        rows = json.loads(record.read_text())
        assert rows and all(key in row for row in rows for key in RECORD_KEYS), f"{record.name} lacks {RECORD_KEYS}"
        trained = [row for row in rows if any(key in row for key in TRAINING_KEYS)]
        assert all(key in row for row in trained for key in TRAINING_KEYS), f"{record.name} lacks {TRAINING_KEYS}"
        assert all(row["machine"].get("cpu_count") for row in rows)


def test_bench_provenance_names_this_commit_and_machine() -> None:
    where = provenance()
    if (REPO / ".git").exists():
        assert where["commit"] and re.fullmatch(r"[0-9a-f]{40}", where["commit"])
    assert where["machine"]["cpu_count"] >= 1 and where["machine"]["torch"]
    row = {"name": "fast", **where, "date": "now", "device": "cpu", "load_average_start": [3.5, 2.0, 1.0]}
    (line,) = provenance_lines([row, {"name": "old row without provenance"}])
    assert line.startswith("- fast: commit ") and "load average 3.5" in line and "device cpu" in line
    # torch's CPU kernels say which vector instructions they use: rows from an AVX-512 and an AVX2 machine differ
    assert where["machine"]["cpu_vectors"] in ("DEFAULT", "VSX", "ZVECTOR", "SVE256", "AVX2", "AVX512")
    assert f", {where['machine']['cpu_vectors']})" in line


def test_a_record_written_earlier_does_not_make_the_next_measurement_uncommitted(tmp_path, monkeypatch) -> None:
    """Records are written one after another from one commit: a changed record is no changed code, a changed source
    file is."""
    import subprocess

    from recon.app import bench

    def git(*args: str) -> None:
        subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", *args], check=True,
                       capture_output=True)

    (tmp_path / bench.RECORDS).mkdir(parents=True)
    (tmp_path / bench.RECORDS / "a.json").write_text("[]")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("init", "-q")
    git("add", "-A")
    git("commit", "-qm", "start")
    monkeypatch.setattr(bench, "REPO", tmp_path)
    assert provenance()["uncommitted_changes"] is False
    (tmp_path / bench.RECORDS / "a.json").write_text("[{}]")
    assert provenance()["uncommitted_changes"] is False
    (tmp_path / "code.py").write_text("x = 2\n")
    assert provenance()["uncommitted_changes"] is True
