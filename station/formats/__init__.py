"""Validators for the files a scan folder or a source dataset may hold: one per format, used by every reader.

Floor 1, beside `scanfolder.py`: the stages above all read these formats, so the checks live below
them once. Every error is a `FormatError` naming the file and the field.
"""
