"""dyn_node.audit.cli: the one error handling and the one set of audit options of dyn-audit and dyn-fleet."""
from __future__ import annotations

import errno

import pytest

from dyn_node.audit import bag_audit as audit

from dyn_node.fleet import engine as fleet  # fleet imports Ray only when its engine starts
from dyn_node.bag.reader import BagError
from dyn_node.audit.cli import EXIT_INTERRUPTED, run_command
from dyn_node.errors import ModelError


def _raise(exc: BaseException):
    def work():
        raise exc
    return work


def _never(_):
    raise AssertionError("report ran after a failure")


@pytest.mark.parametrize("exc,line", [
    (BagError("bag x is unreadable", code="bag_unreadable"), "dyn-x: error: bag x is unreadable"),
    (ModelError("no such robot"), "dyn-x: error: no such robot"),
    (FileNotFoundError(errno.ENOENT, "No such file or directory", "/nope"),
     "dyn-x: error: No such file or directory: /nope"),
    (PermissionError(errno.EACCES, "Permission denied"), "dyn-x: error: Permission denied"),
])
def test_input_errors_are_one_line_and_exit_2(exc, line, capsys):
    assert run_command("dyn-x", _raise(exc), _never) == 2
    err = capsys.readouterr().err
    assert err == line + "\n"


def test_interrupt_is_130_and_a_result_goes_to_report(capsys):
    assert run_command("dyn-x", _raise(KeyboardInterrupt()), _never) == EXIT_INTERRUPTED == 130
    assert capsys.readouterr().err == "dyn-x: interrupted\n"
    assert run_command("dyn-x", lambda: 41, lambda r: r + 1) == 42


def test_a_bug_is_not_reported_as_input():
    with pytest.raises(ZeroDivisionError):
        run_command("dyn-x", lambda: 1 / 0, _never)


def test_both_commands_read_the_audit_options_alike(tmp_path):
    opts = ["--robot-model", "ur5", "--limits", "l.yaml", "--topics", "/a", "/b",
            "--gap-threshold", "0.2", "--no-report"]
    a = vars(audit.build_parser().parse_args(["bag", *opts]))
    f = vars(fleet.build_parser().parse_args(["root", "--out", str(tmp_path), *opts]))
    keys = ("robot_model", "robot_description", "limits", "topics", "gap_threshold", "no_report")
    assert {k: a[k] for k in keys} == {k: f[k] for k in keys} == {
        "robot_model": "ur5", "robot_description": "", "limits": "l.yaml", "topics": ["/a", "/b"],
        "gap_threshold": 0.2, "no_report": True}
    defaults = ("bag",), ("root", "--out", str(tmp_path))
    a0, f0 = (vars(p.parse_args(list(d))) for p, d in zip((audit.build_parser(), fleet.build_parser()), defaults))
    assert {k: a0[k] for k in keys} == {k: f0[k] for k in keys}
    for p, d in zip((audit.build_parser(), fleet.build_parser()), defaults):
        with pytest.raises(SystemExit):  # one model source at a time, in both
            p.parse_args([*d, "--robot-model", "ur5", "--robot-description", "x.urdf"])


@pytest.mark.parametrize("module", ["dyn_node.audit.bag_audit", "dyn_node.audit"])
def test_audit_command_freezes_the_start_up_and_keeps_the_collector(module, tmp_path):
    """Run as a command, main() freezes the start-up's objects (no collection walks them) and
    leaves the collector on (a long audit's cyclic garbage is collected). Imported as a module,
    the caller's collector is never touched."""
    import subprocess
    import sys

    code = ("import gc, runpy, sys\n"
            f"sys.argv = ['dyn-audit', {str(tmp_path / 'none')!r}, '--out', {str(tmp_path / 'o')!r}]\n"
            "try:\n"
            f"    runpy.run_module({module!r}, run_name='__main__', alter_sys=True)\n"
            "except SystemExit as e:\n"
            "    print(e.code, gc.isenabled(), gc.get_freeze_count() > 0)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["2", "True", "True"], out.stderr
    probe = "import gc, dyn_node.audit.bag_audit, dyn_node.audit.__main__; print(gc.isenabled(), gc.get_freeze_count())"
    assert subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          timeout=120).stdout.split() == ["True", "0"]
