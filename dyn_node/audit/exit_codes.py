"""Exit codes of every command that audits (dyn-audit, dyn-check, dyn-fleet): one mapping.

0 everything feasible; 1 violations found (wins over 3: the evidence still says partial);
2 unusable input (nothing could be audited); 3 partial: parts of the input could not be read and
what was read is feasible (as dyn-bag-recover's 3 means "some data lost"). A script that only
looks at the exit code never mistakes a partial audit for a clean one.
"""
from __future__ import annotations

EXIT_OK, EXIT_VIOLATIONS, EXIT_UNUSABLE, EXIT_PARTIAL = 0, 1, 2, 3

#: What each code means, for --help texts and docs/audit.md "Exit codes".
MEANINGS: dict[int, str] = {
    EXIT_OK: "everything feasible",
    EXIT_VIOLATIONS: "violations found",
    EXIT_UNUSABLE: "unusable input",
    EXIT_PARTIAL: "partial: some input unreadable, no violations in the rest",
}


def exit_code(*, violations: bool, partial: bool, unusable: bool = False) -> int:
    """The exit code for an audit outcome: unusable (2) > violations (1) > partial (3) > ok (0)."""
    if unusable:
        return EXIT_UNUSABLE
    if violations:
        return EXIT_VIOLATIONS
    return EXIT_PARTIAL if partial else EXIT_OK
