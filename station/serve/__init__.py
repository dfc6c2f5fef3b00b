"""`station serve`: the operator's dashboard (floor 5).

A FastAPI app (app.py) over a scan runner that owns the rig while a scan runs (rig_control.py),
a read-only view of the overnight queue and its reports (scans.py), and a plain HTML page with a
little vanilla JavaScript that polls the JSON API (static/).
"""
