"""Reading the CSV files the scripts take (evaluate's results.csv, crash logs) with clear errors."""

from __future__ import annotations

import argparse
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


def add_table_arguments(ap: argparse.ArgumentParser, csv_help: str, labels_default: str) -> None:
    """The arguments of a script that reads several evaluate tables of one model: the files, --labels, --model."""
    ap.add_argument("csv", nargs="+", help=csv_help)
    ap.add_argument("--labels", nargs="+", help=f"a name for each table (default: {labels_default})")
    ap.add_argument("--model", default="sam", help="the model column's value to read (default sam)")


def table_labels(ap: argparse.ArgumentParser, args: argparse.Namespace, default: list[str]) -> list[str]:
    """--labels, or `default`; a usage error when their number is not the number of tables."""
    labels = args.labels or default
    if len(labels) != len(args.csv):
        ap.error(f"--labels: {len(labels)} names for {len(args.csv)} tables")
    return labels
