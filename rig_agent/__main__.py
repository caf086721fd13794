"""The scanner PC's agent: calibrate, scan, resume, check, upload, status, clean.

Errors are printed as one plain message (no traceback) with an exit code:
0 done, 1 quality check or upload refused, 2 bad arguments or settings,
3 the rig stopped (the scan can be resumed), 4 the library could not be reached.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence

from tqdm import tqdm

from rig_agent import workflow
from rig_agent.acquire import ScanInterrupted
from rig_agent.assemble import AssemblyError
from rig_agent.devices.base import DeviceError
from rig_agent.fsutil import read_json
from rig_agent.plan import PlanError
from rig_agent.settings import Settings, SettingsError, load_settings
from rig_agent.spool import Spool, SpoolError, SpoolScan
from rig_agent.upload import LibraryClient, UploadError, upload_scan


class CliError(Exception):
    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def _bar(desc: str, unit: str = "frame", **kw):
    bar = tqdm(desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True, **kw)

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    return bar, update


def _capture_and_finish(scan: SpoolScan, settings: Settings, spool: Spool) -> int:
    kind = scan.meta["kind"]
    print(f"{kind} {scan.id} → {scan.path}")
    bar, update = _bar(f"capturing {kind} {scan.id[:8]}")
    try:
        workflow.run_capture(scan, settings, progress=update)
    except ScanInterrupted as exc:
        raise CliError(str(exc), 3) from None
    finally:
        bar.close()
    report = workflow.finish(scan, spool)
    print(report.to_text())
    if kind == "calibration":
        print(f"calibration {scan.id[:8]} is ready; scans will use it.")
    elif report.ok:
        print(f"scan {scan.id[:8]} is ready to upload: rig-agent upload {scan.id[:8]}")
    else:
        print(
            f"scan {scan.id[:8]} is NOT ready: fix the problems and scan again, or upload "
            f"anyway with `rig-agent upload --force {scan.id[:8]}`"
        )
    return 0 if report.ok else 1


def cmd_calibrate(args, settings: Settings, spool: Spool) -> int:
    scan = workflow.start(settings, spool, kind="calibration")
    return _capture_and_finish(scan, settings, spool)


def cmd_scan(args, settings: Settings, spool: Spool) -> int:
    tablet = {"designation": args.tablet}
    if args.museum_number:
        tablet["museum_number"] = args.museum_number
    scan = workflow.start(settings, spool, kind="scan", face=args.face, tablet=tablet)
    return _capture_and_finish(scan, settings, spool)


def cmd_resume(args, settings: Settings, spool: Spool) -> int:
    if args.scan:
        scan = spool.open(args.scan)
    else:
        unfinished = [s for s in spool.scans() if s.pending()]
        if not unfinished:
            print("nothing to resume: every scan in the spool is complete")
            return 0
        scan = unfinished[-1]
    if not scan.pending():
        print(f"{scan.id[:8]} has every frame; checking and bundling it again")
        report = workflow.finish(scan, spool)
        print(report.to_text())
        return 0 if report.ok else 1
    return _capture_and_finish(scan, settings, spool)


def cmd_check(args, settings: Settings, spool: Spool) -> int:
    report = workflow.check(spool.open(args.scan))
    print(report.to_text())
    return 0 if report.ok else 1


def cmd_upload(args, settings: Settings, spool: Spool) -> int:
    scans = [spool.open(s) for s in args.scan] or [
        s for s in spool.scans() if s.meta["kind"] == "scan" and s.state.get("phase") == "bundled"
    ]
    if not scans:
        print("nothing to upload")
        return 0
    client = LibraryClient(
        settings.library_url,
        settings.api_token,
        retries=settings.upload_retries,
        backoff_s=settings.upload_backoff_s,
        timeout_s=settings.upload_timeout_s,
    )
    try:
        for scan in scans:
            quality = scan.path / "quality.json"
            if not quality.exists():
                raise CliError(
                    f"scan {scan.id[:8]} has not been checked: run `rig-agent resume`", 1
                )
            if not read_json(quality)["ok"] and not args.force:
                raise CliError(
                    f"scan {scan.id[:8]} failed its quality check (`rig-agent check "
                    f"{scan.id[:8]}` shows why); use --force to upload it anyway",
                    1,
                )
            designation = scan.meta["tablet"].get("designation")
            tablet_id = args.tablet_id or client.find_tablet(designation)
            bar, update = _bar(f"uploading {scan.id[:8]}", unit="B", unit_scale=True)
            try:
                result = upload_scan(scan, client, tablet_id=tablet_id, progress=update)
            finally:
                bar.close()
            print(
                f"scan {scan.id[:8]} uploaded: library scan {result['scan']['id']}, "
                f"reconstruction job {result['job']['id']}"
            )
    finally:
        client.close()
    return 0


def cmd_status(args, settings: Settings, spool: Spool) -> int:
    scans = spool.scans()
    if not scans:
        print(f"the spool {spool.root} is empty")
        return 0
    print(f"{'id':8}  {'kind':11}  {'tablet':12}  {'face':8}  {'frames':>9}  {'state':12}  upload")
    for scan in scans:
        meta, state = scan.meta, scan.state
        total = len(scan.shots)
        done = total - len(scan.pending())
        upload = state.get("upload") or {}
        if state.get("phase") == "uploaded":
            sent = "confirmed"
        elif upload.get("size_bytes"):
            received = sum(b - a for a, b in upload.get("ranges") or [])
            sent = f"{received / upload['size_bytes']:.0%}"
        else:
            sent = "-"
        print(
            f"{scan.id[:8]}  {meta['kind']:11}  {(meta.get('tablet') or {}).get('designation') or '-':12}  "
            f"{meta.get('face') or '-':8}  {done:>4}/{total:<4}  {state.get('phase', '?'):12}  {sent}"
        )
        if state.get("problem"):
            print(f"          problem: {state['problem']}")
    return 0


def cmd_clean(args, settings: Settings, spool: Spool) -> int:
    removed = 0
    for scan in spool.scans():
        state = scan.state
        confirmed = (state.get("upload") or {}).get("confirmed_sha256")
        if state.get("phase") == "uploaded" and confirmed:
            spool.remove(scan)
            removed += 1
    print(f"removed {removed} uploaded scan(s) whose checksum the library confirmed")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rig-agent", description=__doc__.splitlines()[0])
    parser.add_argument("--config", help="TOML settings file (default: $RIG_AGENT_CONFIG)")
    parser.add_argument("--sim", action="store_true", help="use the simulated rig")
    parser.add_argument(
        "--projector-screen",
        type=int,
        metavar="N",
        help="display index of the projector (overrides the projector_screen setting)",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("calibrate", help="capture the white reference target")
    scan = sub.add_parser("scan", help="capture one face of a tablet")
    scan.add_argument("--tablet", required=True, help="designation, e.g. a CDLI P-number")
    scan.add_argument("--face", required=True, choices=workflow.FACES)
    scan.add_argument("--museum-number")
    resume = sub.add_parser("resume", help="continue an interrupted scan")
    resume.add_argument("scan", nargs="?", help="scan id (or its first characters)")
    check = sub.add_parser("check", help="run the quality check again")
    check.add_argument("scan")
    upload = sub.add_parser("upload", help="send scans to the library")
    upload.add_argument("scan", nargs="*", help="scan ids (default: every bundled scan)")
    upload.add_argument("--force", action="store_true", help="upload despite quality errors")
    upload.add_argument("--tablet-id", type=int, help="library tablet id (default: by designation)")
    sub.add_parser("status", help="list spooled scans and their upload state")
    sub.add_parser("clean", help="delete scans the library has confirmed")
    return parser


COMMANDS = {
    "calibrate": cmd_calibrate,
    "scan": cmd_scan,
    "resume": cmd_resume,
    "check": cmd_check,
    "upload": cmd_upload,
    "status": cmd_status,
    "clean": cmd_clean,
}


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        settings = load_settings(args.config)
        if args.sim:
            settings = dataclasses.replace(settings, devices="sim")
        if args.projector_screen is not None:
            settings = dataclasses.replace(settings, projector_screen=args.projector_screen)
        spool = Spool(settings.spool_path)
        return COMMANDS[args.command](args, settings, spool)
    except CliError as exc:
        print(f"rig-agent: {exc}", file=sys.stderr)
        return exc.code
    except (SettingsError, PlanError, ValueError) as exc:
        print(f"rig-agent: {exc}", file=sys.stderr)
        return 2
    except (DeviceError, SpoolError, AssemblyError) as exc:
        print(f"rig-agent: {exc}", file=sys.stderr)
        return 3
    except UploadError as exc:
        print(f"rig-agent: {exc}", file=sys.stderr)
        return 4
    except KeyboardInterrupt:
        print(
            "rig-agent: interrupted; every frame captured so far is in the spool", file=sys.stderr
        )
        return 130


if __name__ == "__main__":
    sys.exit(main())
