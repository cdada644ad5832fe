"""``dp5k capture``, ``dp5k devices`` and ``dp5k verify``."""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import _thread
from collections.abc import Iterator
from pathlib import Path

import click

from dp5k_common.cli_conventions import out_option
from dp5k_common.errors import BadInputError, DatasetFormatError, DP5KError

log = logging.getLogger(__name__)

CTRL_C_AGAIN_S = 0.05  # a Ctrl-C swallowed by a finalizer is delivered again this much later


@click.command("capture")
@click.option("--scene", required=True, help="Scene name (one folder under --out): 1-100 letters, digits, '.', '_', '-'; "
              "not starting with '.' or '-', no Windows device names (CON, NUL, COM1, ...). With --sim: a studio preset: "
              "demo01, wall, plane (dp5k process calibrates them), boxes (from --sim-scale medium on), near (close-ups "
              "for studio datasets: its two bodies focus 0.6 and 2.6 m away, too far apart to calibrate); a seed (17, "
              "rand17); or any other name, which picks a random studio scene that the rig can focus and calibrate in "
              "(the same name, the same scene).")
@out_option("Raw session root; the scene goes to OUT/SCENE. Created if missing (when its nearest existing parent is "
            "writable); an unwritable OUT is refused before any device is touched. An interrupted scene resumes; a "
            "captured file is never overwritten.", default=Path("raw"), resumes=True)
@click.option("--rig", "rig_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="rig.toml (body serials, focus points, projector port, exposure plan).")
@click.option("--sim", is_flag=True, help="Capture from the simulated rig (simulated bodies on a simulated USB bus, projector on a pty, virtual studio).")
@click.option("--sim-scale", default="small", show_default=True, help="Studio scale for --sim: small (336x224 raw, the smallest that processing calibrates reliably), medium, paper, or a sensor downscale factor.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Studio seed for --sim.")
@click.option("--sim-faults", default="", help="Faults of the simulated bodies, e.g. 'disconnect@37,busy=0.1' or 'cam1.hang@5' "
              "(disconnect/stall/hang@K: during the K-th raw download; busy=P: DeviceBusy with probability P; CAM. = one body).")
@click.option("--sim-rig", "sim_rig", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Unix socket of a simulated rig running in its own process (python -m dp5k_capture.sim.server); "
              "its bodies outlive this command, as real ones do. Implies --sim.")
@click.option("--dry-run", is_flag=True, help="Print the plan (and what a resume would skip); touch nothing.")
def capture_command(scene: str, out: Path, rig_path: Path | None, sim: bool, sim_scale: str, seed: int, sim_faults: str,
                    sim_rig: Path | None, dry_run: bool) -> None:
    """Capture one scene: 10 DP + 2 sharp raws, 6 ChArUco, 92 structured-light images (2 bodies).

    Resumes an interrupted scene; never overwrites a captured file; errors name the device and step.
    """
    from .capture import describe_plan
    from .paths import check_out_dir, check_scene_name
    from .rig import RigConfig, load_rig
    from .rawsession import FORMAT

    check_scene_name(scene)
    check_out_dir(out, create=False)
    sim = sim or sim_rig is not None
    if sim_faults and not sim:
        raise BadInputError("fault injection needs the simulated rig (--sim or --sim-rig)", where="--sim-faults")
    rig = load_rig(rig_path) if rig_path else RigConfig()
    if sim_faults:
        from .sim.fault_spec import parse_sim_faults

        parse_sim_faults(sim_faults, tuple(b.id for b in rig.bodies))  # a typo fails before anything starts
    if dry_run:
        for line in describe_plan(rig, scene, out, "dng" if sim else "CR2"):
            click.echo(line)
        manifest = out / scene / "manifest.json"
        if manifest.is_file():
            from dp5k_common.io import read_json

            m = read_json(manifest)
            if m.get("format") == FORMAT:
                state = "complete (would refuse)" if m.get("complete") else f"incomplete: {len(m.get('files', []))} files done, would resume"
                click.echo(f"existing session: {state}")
                if not m.get("complete"):
                    from .resume import describe_resume

                    for line in describe_resume(m):
                        click.echo(f"  resume: {line}")
        if sim:
            click.echo("simulated rig: bodies and raw sizes come from the studio at run time")
        return
    from .session_run import SimSpec, capture_scene

    scale = float(sim_scale) if sim_scale.replace(".", "", 1).isdigit() else sim_scale
    spec = SimSpec(scale, seed, faults=sim_faults, server=sim_rig) if sim else None
    try:
        with ctrl_c_from_finalizers():
            result = capture_scene(scene, out, rig, sim=spec, prompt=lambda msg: click.prompt(msg, default="", show_default=False))
    except (KeyboardInterrupt, click.exceptions.Abort):  # click.prompt turns a Ctrl-C at the board prompt into Abort
        click.echo(f"dp5k: interrupted: {_kept(out / scene)}", err=True)
        click.get_current_context().exit(130)
    click.echo(f"{result.dir}: complete ({result.written} files captured now)")


@contextlib.contextmanager
def ctrl_c_from_finalizers() -> Iterator[None]:
    """A Ctrl-C that lands while the garbage collector runs a finalizer (a weakref callback, a ``__del__``) is
    "ignored" by Python, which prints its traceback on stderr and goes on. Deliver it to the main thread again
    instead (from a timer thread, so it arrives after the finalizer, not inside this hook), so it ends the
    command like any Ctrl-C: one line, exit code 130."""
    previous = sys.unraisablehook

    def hook(unraisable: sys.UnraisableHookArgs) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            again = threading.Timer(CTRL_C_AGAIN_S, _thread.interrupt_main)
            again.daemon = True
            again.start()
            return
        previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _kept(session_dir: Path) -> str:
    """What an interrupted capture left (the completed files the manifest records) and what to do."""
    from dp5k_common.io import read_json

    try:
        manifest = read_json(session_dir / "manifest.json")
        n, complete = len(manifest.get("files", [])), bool(manifest.get("complete"))
    except (DP5KError, OSError, AttributeError):
        n, complete = 0, False
    if complete:  # the Ctrl-C came after the session was marked complete
        return f"{session_dir} is complete ({n} files); nothing to resume"
    kept = f"{n} completed files kept in {session_dir}" if n else f"no file was captured in {session_dir}"
    return f"{kept}; run the same command again to resume"


@click.command("devices")
@click.option("--rig", "rig_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="rig.toml: names the bodies (cam0/cam1 by serial) and the projector's port, which is then asked over ESC/VP21.")
@click.option("--sim", is_flag=True, help="List the simulated rig's devices instead.")
@click.option("--sim-faults", default="", help="Faults of the simulated bodies, as for capture (e.g. 'cam1.denied', 'cam0.held').")
@click.option("--udev-rule", is_flag=True, help="Print dp5k's udev rules file and exit; install it with "
              "dp5k devices --udev-rule | sudo tee /etc/udev/rules.d/60-dp5k.rules.")
def devices_command(rig_path: Path | None, sim: bool, sim_faults: str, udev_rule: bool) -> None:
    """List every Canon body (model, serial, device node, permission, battery, card free space, who holds it) and
    the serial ports for the EPSON projector (permission, holder; the rig's port is asked for serial and power)."""
    from .device_report import probe_body, probe_port
    from .devices import find_bodies, serial_ports
    from .rig import RigConfig, load_rig
    from .usb_access import udev_rule_path

    if udev_rule:
        click.echo(udev_rule_path().read_text(), nl=False)
        return
    if sim_faults and not sim:
        raise BadInputError("fault injection needs the simulated rig (--sim)", where="--sim-faults")
    rig = load_rig(rig_path) if rig_path else RigConfig()
    closer = None
    if sim:
        from .sim.world import make_sim_rig

        s = make_sim_rig(rig, faults=sim_faults)
        rig, closer = s.rig, s.close
        bodies, ports, query = find_bodies(s.backend), [(s.rig.projector.port, "simulated EPSON EB-U42 (ESC/VP21)")], {s.rig.projector.port}
    else:
        bodies = find_bodies()
        ports = [(p.split("  ", 1)[0], p.split("  ", 1)[-1]) for p in serial_ports()]
        query = {rig.projector.port} if rig_path else set()
        if rig_path:  # the rig's projector: its model from rig.toml (ESC/VP21 has no model query)
            ports = [(p, d) for p, d in ports if p != rig.projector.port]
            ports.append((rig.projector.port, f"{rig.projector.model} (rig.toml's projector port)"))
    ids = {b.serial: b.id for b in rig.bodies if b.serial}
    try:
        click.echo(f"Canon bodies ({len(bodies)}):")
        for found in bodies:
            lines = probe_body(found).lines()
            cam = ids.get(found.serial)
            click.echo(f"  {cam + ': ' if cam else ''}{lines[0]}")
            for line in lines[1:]:
                click.echo(f"  {line}")
        click.echo(f"EPSON projector: serial ports ({len(ports)}):")
        for port, desc in ports:
            for i, line in enumerate(probe_port(port, desc, query=port in query).lines()):
                click.echo(f"  {line}")
        if not query:
            click.echo("  (the projector is asked for its serial number and power on the port that --rig names)")
    finally:
        if closer:
            closer()


@click.command("verify")
@click.argument("scenes", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--no-dp-check", is_flag=True, help="Skip opening every raw with rawpy (sizes and SHA-256 only).")
def verify_command(scenes: tuple[Path, ...], no_dp_check: bool) -> None:
    """Verify raw sessions: every file's size and SHA-256, the per-kind counts, Dual Pixel frames.

    A processed dataset (format v1, a folder with dataset.json) is checked by dp5k check; given one, verify says
    so and runs that check.
    """
    from dp5k_common.check import echo_check

    from .rawsession import verify_session

    bad = 0
    for scene in scenes:
        if not (scene / "manifest.json").is_file():
            if (scene / "dataset.json").is_file():
                click.echo(f"{scene}: a processed dataset (format v1), not a raw session: running dp5k check {scene}",
                           err=True)
                echo_check(scene)
                continue
            raise BadInputError("no manifest.json: not a raw capture session (a processed dataset is checked with "
                                "dp5k check DATASET)", where=scene)
        report = verify_session(scene, check_dual_pixel=not no_dp_check)
        counts = ", ".join(f"{k} {v}" for k, v in report.counts.items())
        status = "OK" if not report.problems else f"{len(report.problems)} problems"
        click.echo(f"{scene}: {status}: {report.files} files, {report.bytes / 1e6:.1f} MB ({counts})")
        for p in report.problems:
            click.echo(f"  {p}")
        bad += bool(report.problems)
    if bad:
        raise DatasetFormatError(f"{bad} of {len(scenes)} sessions failed verification", where="verify")
