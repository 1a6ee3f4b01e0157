"""A study's folder and its run: ``samples.csv`` (one row per rig and design, appended as each
arrives, so that a study stopped part-way resumes where it stopped), ``study.json`` (which study
the folder holds), and the study's remaining tasks run on a Dask client (``run_study``)."""

from __future__ import annotations

import csv
import io
import json
import time
from pathlib import Path

from beamctl.common.outputs import replacing, write_text
from beamctl.config.schema import ConfigError
from beamctl.simulation.study import Study, Task, design_texts, run_task, tasks

ROWS = "samples.csv"
STUDY = "study.json"
FIXED_COLUMNS = ("onset_n", "critical_load_n", "ratio", "censored", "reason", "seed")



def _columns(study: Study) -> list[str]:
    return ["sample", "design", *study.parameters, *FIXED_COLUMNS]


def _read_rows(path: Path, study: Study) -> list[dict]:
    """The rows already written (a resumed study), typed; a last line cut short when the study
    was stopped is dropped; a file of another study is refused."""
    text = path.read_text(encoding="utf-8")
    if text and not text.endswith("\n"):
        text = text[:text.rfind("\n") + 1]
    reader = csv.DictReader(io.StringIO(text))
    if reader.fieldnames != _columns(study):
        raise ConfigError("--out", str(path.parent), "a folder of this study (its samples.csv has other "
                          "columns): give another folder")
    rows = []
    for r in reader:
        typed: dict = {"sample": int(r["sample"]), "design": r["design"], "censored": r["censored"] == "true",
                       "reason": r["reason"], "seed": int(r["seed"])}
        for k in (*study.parameters, "onset_n", "critical_load_n", "ratio"):
            typed[k] = float(r[k])
        rows.append(typed)
    return rows


def _write_rows(path: Path, study: Study, rows: list[dict]) -> None:
    """samples.csv whole: the header and ``rows`` (a resumed study starts from a clean file)."""
    with replacing(path) as temp, open(temp, "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=_columns(study))
        writer.writeheader()
        writer.writerows(map(_csv_row, rows))


def _csv_row(row: dict) -> dict:
    """A row as written: ``censored`` as true or false."""
    return {**row, "censored": "true" if row["censored"] else "false"}


def prepare(study: Study, out: Path) -> list[dict]:
    """The folder of the study: its rows so far (resume) or a new samples.csv with its header."""
    rows_path, study_path = out / ROWS, out / STUDY
    if study_path.exists():
        recorded = json.loads(study_path.read_text())
        if recorded.get("digest") != study.digest():
            raise ConfigError("--out", str(out), f"a folder of this study: it holds another study "
                              f"({recorded.get('source', '?')}); give another folder")
    else:
        write_text(study_path, json.dumps({"digest": study.digest(), "source": study.source,
                                           "study": study.to_dict()}, indent=1))
    rows = _read_rows(rows_path, study) if rows_path.exists() else []
    _write_rows(rows_path, study, rows)
    return rows


def run_study(study: Study, out: Path, client, progress=None) -> tuple[list[dict], dict]:
    """Run the study's remaining tasks on ``client`` (a dask.distributed Client), appending each
    row to ``out/samples.csv`` as it arrives; return all rows and the counts."""
    from distributed import as_completed

    rows = prepare(study, out)
    done = {(r["sample"], r["design"]) for r in rows}
    todo: list[Task] = tasks(study, done)
    total = study.samples * len(study.designs)
    start = time.monotonic()
    keys = [f"beamctl-study-{study.digest()[:12]}-{t.sample}-{study.designs.index(t.design)}" for t in todo]
    futures = []
    if todo:        # the tables travel once to each worker, not with every task
        texts = client.scatter([design_texts(study)], broadcast=True)[0]
        futures = client.map(run_task, todo, [texts] * len(todo), key=keys, pure=False)
    columns = _columns(study)
    new = 0
    try:
        with open(out / ROWS, "a", newline="", encoding="utf-8") as f:
            writer = csv.DictWriter(f, fieldnames=columns)
            for future in as_completed(futures):
                row = {**future.result(), "seed": study.seed}
                writer.writerow(_csv_row(row))
                f.flush()
                rows.append(row)
                new += 1
                if progress is not None:
                    elapsed = time.monotonic() - start
                    rate = new / elapsed if elapsed > 0 else 0.0
                    # the samples to run now (the bar's time left is theirs, not the resumed ones')
                    before = f", {total - len(todo)} from before" if len(todo) < total else ""
                    progress(new, len(todo), f"{rate:.2f}/s{before}")
    finally:
        for future in futures:
            future.cancel()
    return rows, {"resumed": total - len(todo), "run": new, "wall_s": time.monotonic() - start}
