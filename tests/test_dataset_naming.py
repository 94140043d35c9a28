"""Dataset names the BOP toolkit can read back from results file names, and the old name ``ycbv-synth``.

The toolkit (``inout.parse_result_filename``) cuts the base name at the first ``.``, splits it on
``_`` (method, then DATASET-SPLIT[-SPLITTYPE]) and the second part on ``-``.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from bop_fixtures import write_tiny_bop

from cosy_lite.bop.dataset import BopDataset
from cosy_lite.bop.folders import dataset_folder
from cosy_lite.bop.params import DATASETS, RENAMED_DATASETS, get_dataset_params
from cosy_lite.bop.results import (
    PoseEstimate,
    misread_dataset,
    parse_results_filename,
    results_filename,
    toolkit_parse_results_filename,
    write_results_csv,
)
from cosy_lite.bop.validate import check_results
from cosy_lite.errors import BopFormatError


def test_no_dataset_name_has_a_toolkit_separator():
    for name in DATASETS:
        assert "-" not in name and "_" not in name, name
    assert RENAMED_DATASETS == {"ycbv-synth": "ycbvsynth"}
    assert get_dataset_params("ycbvsynth").obj_ids == tuple(range(1, 22))


@pytest.mark.parametrize("file_name, expected", [
    ("cosylite_ycbvsynth-test.csv", ("cosylite_ycbvsynth-test", "cosylite", "ycbvsynth", "test", None, "csv")),
    ("/a/b/m-v2_tless-test-primesense.csv", ("m-v2_tless-test-primesense", "m-v2", "tless", "test", "primesense", "csv")),
    ("m_lmo-test_abc123.json.gz", ("m_lmo-test_abc123", "m", "lmo", "test", None, "json.gz")),
    # the old name: the toolkit reads dataset "ycbv", split "synth", split type "test"
    ("cosylite_ycbv-synth-test.csv", ("cosylite_ycbv-synth-test", "cosylite", "ycbv", "synth", "test", "csv")),
])
def test_toolkit_rule(file_name: str, expected: tuple):
    assert tuple(toolkit_parse_results_filename(file_name)) == expected


def test_toolkit_rule_fails_where_the_toolkit_does():
    for bad in ("cosylite.csv", "cosylite_ycbv.csv"):
        with pytest.raises(BopFormatError, match="cannot read"):
            toolkit_parse_results_filename(bad)


def test_correct_names_parse_as_method_dataset_split_both_ways():
    for method, dataset, split in (("cosylite", "ycbvsynth", "test"), ("m-v2", "tiny", "test"), ("x", "lmo", "test")):
        name = results_filename(method, dataset, split)
        t = toolkit_parse_results_filename(name)
        assert (t.method, t.dataset, t.split, t.split_type) == (method, dataset, split, None)
        assert parse_results_filename(name) == (method, dataset, split)
        assert misread_dataset(name) is None


def test_writer_refuses_dataset_names_the_toolkit_misreads():
    with pytest.raises(ValueError, match=r"dataset 'ycbv-synth'.*'-'"):
        results_filename("cosylite", "ycbv-synth", "test")
    with pytest.raises(ValueError, match=r"method 'v1\.2'"):
        results_filename("v1.2", "ycbvsynth", "test")


def test_dots_and_extra_parts_are_refused():
    with pytest.raises(BopFormatError, match="first '.'"):
        parse_results_filename("m.v2_ycbvsynth-test.csv")
    with pytest.raises(BopFormatError, match="would ignore 'x'"):
        parse_results_filename("m_tless-test-primesense-x.csv")


def _one_estimate_csv(folder: Path, name: str) -> Path:
    path = folder / name
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n0,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 700,0.5")
    return path


def test_check_results_names_the_misread_and_the_new_name(tmp_path: Path):
    path = _one_estimate_csv(tmp_path, "cosylite_ycbv-synth-test.csv")
    errors = [p for p in check_results(path) if p.severity == "error"]
    assert len(errors) == 1 and errors[0].field == "file name"
    msg = errors[0].message
    assert "reads dataset 'ycbv', split 'synth', split type 'test'" in msg
    assert "cosylite_ycbvsynth-test.csv" in msg
    ok = _one_estimate_csv(tmp_path, "cosylite_ycbvsynth-test.csv")
    assert [p for p in check_results(ok) if p.severity == "error"] == []


def test_check_results_refuses_a_dataset_name_with_a_separator(tmp_path: Path):
    path = _one_estimate_csv(tmp_path, "cosylite_my-test.csv")
    msgs = [p.message for p in check_results(path, name="my-objects") if p.severity == "error"]
    assert any("'my-objects' contains '-' or '_'" in m for m in msgs)


def test_an_old_folder_is_read_under_the_new_name_with_a_warning(tmp_path: Path):
    root = write_tiny_bop(tmp_path, "ycbv-synth")
    with pytest.warns(UserWarning, match=r"now called 'ycbvsynth'.*mv .*ycbv-synth .*ycbvsynth"):
        ds = BopDataset(root)
    assert ds.name == "ycbvsynth"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        TCO = np.eye(4)
        TCO[2, 3] = 0.7
        est = PoseEstimate(0, 0, 1, 0.9, TCO, 0.1)
        out = tmp_path / "out" / results_filename("cosylite", ds.name, "test")
        write_results_csv(out, [est])
    assert out.name == "cosylite_ycbvsynth-test.csv"


def test_dataset_argument_with_the_old_name(tmp_path: Path):
    with pytest.raises(BopFormatError, match=r"now called 'ycbvsynth'.*use --dataset ycbvsynth"):
        dataset_folder("ycbv-synth", tmp_path)
    (tmp_path / "ycbv-synth").mkdir()
    assert dataset_folder("ycbv-synth", tmp_path) == tmp_path / "ycbv-synth"  # old folder: still usable
    (tmp_path / "ycbvsynth").mkdir()
    assert dataset_folder("ycbv-synth", tmp_path) == tmp_path / "ycbvsynth"  # the new one wins
    assert dataset_folder("tiny", tmp_path) == tmp_path / "tiny"
    with pytest.raises(KeyError, match="now called 'ycbvsynth'"):
        get_dataset_params("ycbv-synth")


def test_check_results_names_a_misread_of_the_folder_name(tmp_path: Path):
    root = write_tiny_bop(tmp_path, "my-objects")
    path = _one_estimate_csv(tmp_path, "cosylite_my-objects-test.csv")
    msgs = [p.message for p in check_results(path, root) if p.severity == "error"]
    assert any("reads dataset 'my', split 'objects', split type 'test'" in m and "cosylite_myobjects-test.csv" in m
               for m in msgs), msgs


def test_method_with_underscore_says_how_the_toolkit_reads_it():
    with pytest.raises(BopFormatError, match=r"exactly one '_' \(the BOP toolkit would read method 'm', dataset "
                                             r"'ycbv', split 'test'\)"):
        parse_results_filename("m_ycbv-test_run2.csv")  # the toolkit's optional id: not ours
    with pytest.raises(BopFormatError, match=r"the BOP toolkit cannot read it"):
        parse_results_filename("cosy_lite_ycbv-test.csv")


def test_check_dataset_reports_an_old_folder_name(tmp_path: Path):
    from cosy_lite.bop.validate import check_dataset

    root = write_tiny_bop(tmp_path, "ycbv-synth")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # reported as a problem, not as a Python warning
        problems = check_dataset(root)
    named = [p for p in problems if p.field == "name"]
    assert len(named) == 1 and named[0].severity == "warning" and "mv " in named[0].message


def test_a_missing_dataset_says_where_names_are_looked_up(tmp_path, monkeypatch, capsys):
    """``train.py --dataset ycbv`` without the data: the error names the folder, COSY_LITE_DATA and
    --data-root (it named only the folder)."""
    import train

    monkeypatch.setenv("COSY_LITE_DATA", str(tmp_path))
    assert train.main(["--dataset", "ycbv", "--model", "refiner"]) == 2
    err = capsys.readouterr().err
    assert f"dataset folder {tmp_path / 'ycbv'} not found" in err
    assert "COSY_LITE_DATA" in err and "--data-root" in err and str(tmp_path) in err
    with pytest.raises(BopFormatError, match="COSY_LITE_DATA"):
        BopDataset(tmp_path / "ycbv")
