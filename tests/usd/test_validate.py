"""Validation: the clean fixture passes, each bad fixture fails with its rule alone."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from skinpipe.cli import main
from skinpipe.usd.validate import NOT_APPLICABLE, RULES, validate_file

FIXTURES = Path(__file__).parents[1] / "fixtures" / "usd"
BAD = sorted((FIXTURES / "bad").glob("*.usda"))
CLEAN = sorted((FIXTURES / "clean").glob("*.usda"))


def test_fixture_sets_are_there() -> None:
    assert CLEAN and len(BAD) >= 12


@pytest.mark.parametrize("path", CLEAN, ids=lambda p: p.stem)
def test_clean_assets_pass_every_validator(path: Path) -> None:
    report = validate_file(path)
    assert report.unreadable is None and not report.failed(strict=False)
    # every built-in validator ran; what this USD build cannot check is said, not hidden
    beyond = [p for p in report.problems if p.severity == NOT_APPLICABLE]
    assert [p for p in report.problems if p not in beyond] == []
    assert beyond and all(p.rule == "usdShadeValidators:ShaderSdrCompliance"
                          and "no MaterialX Sdr plugin" in p.message for p in beyond)
    assert report.failed(strict=True)


@pytest.mark.parametrize("path", BAD, ids=lambda p: p.stem)
def test_bad_asset_fails_with_its_rule_and_no_other(path: Path) -> None:
    expected = "skinpipe:" + path.stem.split("_")[0]
    report = validate_file(path)
    assert report.unreadable is None
    assert {p.rule for p in report.problems if p.severity != NOT_APPLICABLE} == {expected}
    assert all(p.sites for p in report.problems)


def test_every_rule_has_a_doc_and_a_bad_fixture() -> None:
    covered = {"skinpipe:" + p.stem.split("_")[0] for p in BAD}
    for rule in RULES:
        assert len(rule.doc) > 40, rule.name
        if rule.name != "skinpipe:SchemaPluginRegistered":  # tested without the plugin below
            assert rule.name in covered, rule.name


def test_cli_output_and_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", str(CLEAN[0])]) == 0
    assert capsys.readouterr().out.strip().endswith("Success!")
    assert main(["validate", str(BAD[0])]) == 1
    out = capsys.readouterr().out
    assert out.strip().endswith("Failed!") and "[skinpipe:" in out


def test_deeply_nested_usda_is_a_clean_failure(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", str(FIXTURES / "unreadable_nested.usda")]) == 2
    assert "nested" in capsys.readouterr().err


def test_json_and_junit_reports(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    junit = tmp_path / "report.xml"
    assert main(["validate", "--json", "--junit", str(junit), str(CLEAN[0]), str(BAD[0])]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert [d["result"] for d in doc] == ["Success", "Failed"]
    suites = ET.parse(junit).getroot().findall("testsuite")
    assert [int(s.get("failures")) for s in suites] == [0, 1]


def test_missing_schema_plugin_fails_loudly(tmp_path: Path) -> None:
    env = {**os.environ, "SKINPIPE_SCHEMA_DIR": str(tmp_path / "nowhere")}
    proc = subprocess.run([sys.executable, "-m", "skinpipe", "validate", str(BAD[0])],
                          capture_output=True, text=True, env=env, check=False)
    assert proc.returncode == 1
    assert "skinpipe:SchemaPluginRegistered" in proc.stdout
    # the other rules still ran
    assert "skinpipe:" + BAD[0].stem.split("_")[0] in proc.stdout


def test_list_rules(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", "--list-rules"]) == 0
    out = capsys.readouterr().out
    assert all(r.name in out for r in RULES)


def test_schema_docs_are_whole_sentences_in_the_registry() -> None:
    # USD's registry keeps a doc's first sentence: no abbreviation may cut it short
    from pxr import Usd

    definition = Usd.SchemaRegistry().FindConcretePrimDefinition("SkinDiffusionProfile")
    for name in definition.GetPropertyNames():
        doc = definition.GetPropertyDefinition(name).GetDocumentation()
        assert doc.endswith((".", ")")) and not doc.endswith(("eq.", "e.g.", "i.e.")), name


def test_plain_usd_users_are_told_about_the_plugin_path() -> None:
    env = {k: v for k, v in os.environ.items() if k != "PXR_PLUGINPATH_NAME"}
    r = subprocess.run([sys.executable, "-m", "skinpipe", "validate", str(CLEAN[0])],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0 and "PXR_PLUGINPATH_NAME" in r.stderr
