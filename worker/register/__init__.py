"""Registration of a tablet's scans into one frame, the merged surface and fatcross plates.

CLI: ``python -m worker.register MODEL_DIR... OUTDIR`` (docs/registration.md).
"""
