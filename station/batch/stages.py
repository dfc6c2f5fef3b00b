"""The stage table and keys, as the batch runner has always imported them.

They live in `station/pipeline.py`, shared with the CLI and the dashboard: one table, one notion
of done. See that module for what a key hashes and when a record counts as finished.
"""

from station.pipeline import (
    STAGE_NAMES,
    STAGES,
    TEMP_FILE,
    Digest,
    StageName,
    StageSpec,
    capture_digest,
    clean_stage,
    code_version,
    finished_record,
    output_digest,
    output_files,
    read_record,
    record_path,
    resumable,
    scan_stage_key,
    stage_key,
    sweep_temp_files,
    write_done,
    write_started,
)

__all__ = ["STAGE_NAMES", "STAGES", "TEMP_FILE", "Digest", "StageName", "StageSpec", "capture_digest", "clean_stage",
           "code_version", "finished_record", "output_digest", "output_files", "read_record", "record_path",
           "resumable", "scan_stage_key", "stage_key", "sweep_temp_files", "write_done", "write_started"]
