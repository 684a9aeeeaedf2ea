"""qtl.config.validate: the transfer node is checked on its own, before any source run is read."""

from __future__ import annotations

import pytest

from qtl.config.validate import check_transfer
from qtl.errors import TransferError
from qtl.transfer import Bayesian, NoTransfer


def test_transfer_checks_read_no_source_run(tmp_path):
    missing = str(tmp_path / "no_such_run")  # a source that would fail to load: the value check comes first
    with pytest.raises(TransferError, match=r"min_compliance must be in \[0, 1\], got 1.5"):
        check_transfer({"source": missing, "min_compliance": 1.5}, Bayesian())
    with pytest.raises(TransferError, match="rule=none ignores θ_s"):
        check_transfer({"source": missing}, NoTransfer())
    check_transfer({"source": missing, "hyperparameters": False}, NoTransfer())  # consistent: nothing is read


@pytest.mark.parametrize(
    ("transfer", "message"),
    [
        ({"compliance": "tip"}, "transfer.compliance must be one of"),
        ({"compliance_bandwidth": "silverman"}, "compliance_bandwidth must be one of scott, none, got 'silverman'"),
        ({"compliance_resolution": float("nan")}, "compliance_resolution must be >= 0"),
        ({"compliance_temperature": 0}, "compliance_temperature must be > 0"),
        ({"compliance": "kernel", "compliance_temperature": 2.0}, "tempers the likelihood ratio only"),
    ],
)
def test_bad_compliance_settings_are_one_line(transfer, message):
    with pytest.raises(TransferError, match=message):
        check_transfer(transfer, NoTransfer())


@pytest.mark.parametrize(
    ("transfer", "message"),
    [
        ({"source": []}, r"transfer.source=\[\] names no source run"),
        ({"source": ["runs/a", 3]}, "every entry must be a run directory, got 3"),
        ({"source": ["runs/a", "runs/a"]}, "names a run twice"),
        ({"source": 5}, "a run directory, a list of them or a directory holding them, got 5"),
        ({"source": ["runs/a", "runs/b"], "select": "vote"}, "transfer.select must be one of compliance, mixture"),
        ({"initial_policy": "runs/a", "hyperparameters": False}, "transfer.initial_policy names one of the sources"),
    ],
)
def test_bad_source_lists_and_select_are_one_line(transfer, message):
    with pytest.raises(TransferError, match=message):
        check_transfer({"hyperparameters": False, **transfer}, NoTransfer())


def test_a_list_of_sources_passes_the_checks_without_reading_them(tmp_path):
    missing = [str(tmp_path / "a"), str(tmp_path / "b")]
    check_transfer({"source": missing, "select": "mixture", "initial_policy": missing[1]}, Bayesian())
