"""User docs and help speak to users: no issue numbers, no internal words of the project's
making (contract files, a shared folder beside the checkout, what "this project's search"
reached, helpers), in the README, every docs page (the generated reference included), the
scenario files' comments, the
--help of every avflow command, and the --help of the workflows the docs tell users to run."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The words; "numba issue 4807" (another project's tracker) is a reference, not ours.
INTERNAL = re.compile(r"(?<!numba )\bissues? #?\d+|\bthe issue's\b|\bissue-\d+|\bcontract\b"
                      r"|\.\./shared|shared/contract|this project's search|\bthe lead\b"
                      r"|\bhelpers?\b", re.I)


def _hits(text: str) -> list[str]:
    return [f"{n}: {line.strip()[:120]}" for n, line in enumerate(text.splitlines(), 1)
            if INTERNAL.search(line)]


def _hooks():
    spec = importlib.util.spec_from_file_location("mkdocs_hooks",
                                                  ROOT / "tools" / "mkdocs_hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_pattern_catches_what_it_should():
    for text in ("(issue 28)", "the issue's target", "the 4 GB target of issue 29",
                 "see `../shared/contract/`", "Same as the contract file",
                 "public material that this project's search can reach", "#foo-issue-27-item-9"):
        assert INTERNAL.search(text), text
    assert not INTERNAL.search("can crash, numba issue 4807")


@pytest.mark.parametrize("page", [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")),
                                  *sorted((ROOT / "scenarios").rglob("*.yaml"))],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_pages(page):
    assert not _hits(page.read_text()), _hits(page.read_text())


def test_generated_reference_pages():
    for name, text in _hooks().generated_pages().items():
        assert not _hits(text), (name, _hits(text))


def test_avflow_help_texts():
    from avflow.cli import build_parser

    parser = build_parser()
    texts = {"avflow": parser.format_help()}
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    texts.update({f"avflow {name}": p.format_help() for name, p in sub.choices.items()})
    assert {"avflow region", "avflow calibrate"} <= set(texts)
    description = " ".join(parser.description.split())
    assert all(name in description for name in sub.choices), description
    for name, text in texts.items():
        assert not _hits(text), (name, _hits(text))


def test_help_of_the_workflows_the_docs_name():
    named = set()
    for page in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]:
        named |= set(re.findall(r"python workflows/(\w+)\.py", page.read_text()))
    assert "calibrate_avakot" in named and "make_region" in named
    for name in sorted(named):
        done = subprocess.run([sys.executable, str(ROOT / "workflows" / f"{name}.py"), "--help"],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, (name, done.stderr[-500:])
        assert not _hits(done.stdout), (name, _hits(done.stdout))


def test_example_scheduler_addresses_are_placeholders():
    address = re.compile(r"tcp://(\d+\.\d+\.\d+\.\d+)")
    for page in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]:
        assert not address.search(page.read_text()), page
