"""Reading the CSV files the scripts take (evaluate's results.csv, crash logs) with clear errors."""

from __future__ import annotations

import csv


def read_csv(path: str, columns: tuple[str, ...], kind: str) -> tuple[list[str], list[dict]]:
    """(header, rows) of the CSV file at `path`; exits with a one-line message when it cannot be read
    or lacks one of `columns` (`kind` names what it should be, e.g. 'a crash log')."""
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            header = list(reader.fieldnames or [])
            missing = [c for c in columns if c not in header]
            if missing:
                raise SystemExit(f"{path}: not {kind}: missing column(s) {', '.join(missing)}")
            return header, list(reader)
    except OSError as e:
        raise SystemExit(f"cannot read {path}: {e.strerror}") from None
