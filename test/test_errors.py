"""One error hierarchy: the reportable errors dyn_node raises are DynNodeErrors (ValueErrors)
defined in dyn_node.errors, and each module raises that class, not a copy."""
from __future__ import annotations

import pytest

from dyn_node.bag import recover as bag_recover, recorder as recording

from dyn_node.audit import check as check_cli, trajectory_files

from dyn_node.fleet import engine as fleet

from dyn_node.core.robot import settings
from dyn_node.errors import (CheckError, DynNodeError, FleetError, RecordingError, RecoverError,
                             SettingsError, TrajectoryFileError)
from dyn_node.bag.recorder import RecorderConfig

MOVED = [(RecordingError, recording), (RecoverError, bag_recover), (SettingsError, settings),
         (TrajectoryFileError, trajectory_files), (CheckError, check_cli), (FleetError, fleet)]


@pytest.mark.parametrize("cls,module", MOVED, ids=lambda x: getattr(x, "__name__", ""))
def test_errors_live_in_the_errors_module_under_dyn_node_error(cls, module):
    assert cls.__module__ == "dyn_node.errors"
    assert issubclass(cls, DynNodeError)
    assert issubclass(cls, ValueError)  # callers that catch ValueError keep catching them
    assert getattr(module, cls.__name__) is cls


def test_recorder_and_recover_raise_dyn_node_errors(tmp_path):
    with pytest.raises(DynNodeError, match="compression"):
        RecorderConfig(directory=str(tmp_path), compression="gzip").validate()
    (tmp_path / "x.mcap").write_bytes(b"not mcap at all")
    with pytest.raises(DynNodeError, match="not an MCAP file"):
        bag_recover.recover_file(tmp_path / "x.mcap", tmp_path / "y.mcap")


def test_fleet_raises_dyn_node_errors_with_a_code(tmp_path):
    with pytest.raises(DynNodeError, match="does not exist") as missing:
        fleet.discover([str(tmp_path / "missing")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(DynNodeError, match="no bags found") as empty:  # before any engine starts
        fleet.run_fleet([str(tmp_path / "empty")], tmp_path / "out", progress=False)
    assert (missing.value.code, empty.value.code) == ("not_found", "no_bags")
