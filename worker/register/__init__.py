"""Registration of a tablet's scans into one frame, the merged surface and fatcross plates.

CLI: ``python -m worker.register MODEL_DIR... OUTDIR`` (docs/registration.md).
"""


def run_job(job_id, session_factory, storage, progress):
    """The tablet registration job (worker.tasks.register_tablet); see worker.register.job."""
    from worker.register.job import run_job as run

    return run(job_id, session_factory, storage, progress)
