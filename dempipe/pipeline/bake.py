"""bake(): scene file in, USD stage out. What `dempipe bake` runs.

    result = bake("examples/quickstart.toml", "out.usdc")

Loads and validates the scene, builds sphere sets (cached) and the Model,
refuses scenes that would blow up at frame 0, simulates, and writes the USD
stage atomically. Frames stream to disk with checkpoints as they are made
(dempipe.pipeline.checkpoint); a guard that stops the bake, an error or a stop signal
still writes every frame done so far, to a clearly named partial file beside
the target, and keeps the last checkpoint for ``resume``.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from dempipe import interrupt
from dempipe.check.sizes import check_run_time
from dempipe.check.stability import ERROR, expected_speeds, soft_contact, tunnelling
from dempipe.errors import DempipeError, ExportError, SceneError, StabilityError
from dempipe.interrupt import StopRequested, signal_name
from dempipe.pipeline.checkpoint import atomic_write
from dempipe.pipeline.lock import WorkLock, work_dir
from dempipe.scene.settings import with_simulation
from dempipe.sim.cores import check_threads
from dempipe.sim.overlap import REFUSE_OVERLAP, WARN_OVERLAP
from dempipe.spheres.cache import SphereCache


@dataclass
class BakeResult:
    """What a bake did: the written path and the figures of --report."""

    path: Path
    report: dict = field(default_factory=dict)
    partial: bool = False


def partial_path(out: Path) -> Path:
    """Where an interrupted or failed bake keeps its frames: NAME.partial.EXT."""
    return out.with_name(f"{out.stem}.partial{out.suffix}")


def parse_frame_range(text: str | None, n_frames: int, first: int) -> tuple[int, int]:
    """'START:END' (inclusive, in frame numbers) → indices into the bake's frames."""
    if not text:
        return 0, n_frames - 1
    try:
        a, b = text.split(":")
        start = int(a) if a.strip() else first
        end = int(b) if b.strip() else first + n_frames - 1
    except ValueError:
        raise SceneError(f"--frames: expected START:END (e.g. 0:48), got {text!r}") from None
    last = first + n_frames - 1
    if start > end:
        raise SceneError(f"--frames: {start}:{end} ends before it starts (give START:END with "
                         f"START <= END, within the scene's frames {first}:{last})")
    if not (first <= start and end <= last):
        part = "is outside" if end < first or start > last else "reaches outside"
        raise SceneError(f"--frames: {start}:{end} {part} the scene's frames {first}:{last} "
                         f"(frame numbers as the output's time codes: the scene's first "
                         f"frame is {first})")
    return start - first, end - first


def check_writable(folder, what: str = "output folder") -> None:
    """Write (then remove) a file in ``folder``, or, if it is missing, in the nearest
    folder above it that exists: an ExportError naming the folder and the OS's reason
    when that fails. Called
    before any work, so a bake never simulates for hours into a folder it cannot
    write (root passes the permission bits, so a real write is the only test)."""
    folder = Path(folder)
    # a missing folder is not created here (a scene error must leave nothing behind):
    # the nearest existing folder above it must take the new one
    where = folder
    while not where.exists() and where != where.parent:
        where = where.parent
    if not where.is_dir():
        raise ExportError(f"{folder}: cannot create the {what} ({where} is not a folder)")
    probe = where / f".dempipe-write-test-{os.getpid()}"
    try:
        with open(probe, "wb") as fh:
            fh.write(b"ok")
        probe.unlink()
    except OSError as exc:
        try:
            probe.unlink()
        except OSError:
            pass
        if where == folder:
            raise ExportError(f"{folder}: the {what} is not writable "
                              f"({exc.strerror or exc})") from None
        raise ExportError(f"{folder}: cannot create the {what} in {where} "
                          f"({exc.strerror or exc})") from None


def _same_file(a, b) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


def check_output_names(out: Path, scene_path=None) -> None:
    """Refuse, before any work, an output that is the scene itself or whose name or
    the names derived from it (work folder, partial file, temporary files) are too
    long for its file system: an ExportError naming the file and the fix."""
    if scene_path is not None and _same_file(out, scene_path):
        raise ExportError(f"{out}: is the scene file; give another -o (e.g. "
                          f"{out.stem}_baked{out.suffix})")
    try:
        limit = os.pathconf(_existing(out.parent), "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    longest = max(len(os.fsencode(n)) for n in (
        f".{out.name}.bake", f".{out.stem}.tmp-{os.getpid()}{out.suffix}",
        f".{out.stem}.partial.tmp-{os.getpid()}{out.suffix}",
        f".{out.name}.tmp-{os.getpid()}"))
    if longest > limit:
        raise ExportError(f"{out}: the file name is too long for its folder's file system "
                          f"(with the bake's work and temporary files, {longest} bytes of "
                          f"{limit}); give a shorter -o")
    if len(os.fsencode(str(out.parent.resolve() / f".{out.name}.bake/state-000000.npz"))) \
            >= 4096:
        raise ExportError(f"{out}: the path is too long for the file system; give a "
                          f"shorter -o")


def check_report_path(report, out, scene_path) -> None:
    """Refuse a --report path that would replace the output, its partial file or the
    scene with JSON (an ExportError naming both)."""
    report, out = Path(report), Path(out)
    for other, what in ((out, "the output"), (partial_path(out), "the output's partial file"),
                        (Path(scene_path), "the scene file")):
        if _same_file(report, other):
            raise ExportError(f"--report {report}: is {what}; give the report its own "
                              f"file (e.g. {out.stem}.json)")


def _existing(folder: Path) -> Path:
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return folder


def remove_stale_temporaries(out: Path) -> None:
    """Temporary files of earlier bakes to ``out`` that were killed while writing
    (``.NAME.tmp-PID.EXT``, the partial file's, a report's): the caller holds the
    work folder's lock, so no live bake is writing them."""
    folder = out.parent
    if not folder.is_dir():
        return
    part = partial_path(out)
    prefixes = (f".{out.stem}.tmp-", f".{part.stem}.tmp-", f".{out.name}.tmp-",
                f".{part.name}.tmp-")
    for p in folder.iterdir():
        if p.name.startswith(prefixes) and p.is_file():
            rest = p.name.split(".tmp-", 1)[1]
            pid = rest.split(".", 1)[0]
            if pid.isdigit() and int(pid) != os.getpid():
                p.unlink(missing_ok=True)


def bake(scene_path, out_path, *, device: str | None = None, layout: str = "instancer",
         frames: str | None = None, threads: int | None = None, cache=None,
         progress=None, warn=None, force: bool = False, resume: bool = False,
         chunk_frames: int | None = None, checkpoint_seconds: float | None = None,
         checkpoints: bool = True, simulation: dict | None = None) -> BakeResult:
    """Bake ``scene_path`` to the USD file ``out_path``; returns a BakeResult.

    device : 'cpu' | 'cuda' | 'auto' (default: the scene's simulation.device)
    layout : 'instancer' | 'xforms' (see docs/usd-output.md)
    frames : 'START:END' frame numbers to write, as the output's time codes (from the
        scene's start frame; the simulation always starts at the first)
    threads : CPU threads, a whole number >= 1, or None: follow the cores other
        processes leave free (sim.cores.CoreShare)
    cache : a dempipe.spheres.cache.SphereCache (None: $DEMPIPE_CACHE_DIR or the user
        cache)
    force : bake even what `dempipe check` refuses (deep frame-0 overlaps, a dt above
        the critical step, tunnelling speeds): the risk is the user's
    progress : callable(frame_index, n_frames, stats) for a progress display
    warn : callable(str) for one-line warnings (default: warnings.warn)
    simulation : settings replacing the scene's ``[simulation]`` ones (the
        SimulationSettings fields, e.g. ``{"resolution": 4}``); how a bare USD stage
        gets dempipe's own settings from the command line
    resume : go on from the checkpoint an interrupted bake to ``out_path`` left
        (docs/faults.md); without one, start at frame 0. On the CPU the result is
        bit-identical to an uninterrupted bake. A checkpoint of another scene,
        settings or dempipe version is refused (CheckpointError).
    chunk_frames, checkpoint_seconds : frames per chunk written to disk and the
        longest wall time between two checkpoints (default: dempipe.pipeline.checkpoint's).
    checkpoints : False keeps no State on disk (chunks of frames still stream);
        an interrupted bake then cannot be resumed.

    Frames stream to disk in chunks beside the output as they are made (memory
    does not grow with the number of frames), each followed by a checkpoint; the
    USD file is assembled from them at the end and the work folder removed. A
    stop signal (SIGINT, SIGTERM, SIGHUP: dempipe.interrupt), a guard that trips
    or a failing write keeps every finished frame in NAME.partial.EXT and the
    checkpoint for --resume.
    """
    if not isinstance(scene_path, (str, os.PathLike)) or not isinstance(out_path,
                                                                        (str, os.PathLike)):
        raise SceneError(f"bake(scene_path, out_path): expected two paths (a .toml scene or a "
                         f"USD stage, and the .usd/.usdc/.usda to write), got "
                         f"{type(scene_path).__name__} and {type(out_path).__name__}")
    with interrupt.installed_for_call():
        try:
            return _bake(scene_path, out_path, device=device, layout=layout, frames=frames,
                         threads=threads, cache=cache, progress=progress, warn=warn,
                         force=force, resume=resume, chunk_frames=chunk_frames,
                         checkpoint_seconds=checkpoint_seconds, checkpoints=checkpoints,
                         simulation=simulation)
        except BakeInterrupted:
            raise                       # the stop, with the frames it kept
        except Exception as exc:        # a stop a library swallowed, failing later
            stop = interrupt.stop_behind(exc)
            if stop is None:
                raise
            raise stop from exc


def _bake(scene_path, out_path, *, device, layout, frames, threads, cache, progress, warn,
          force, resume, chunk_frames, checkpoint_seconds, checkpoints,
          simulation) -> BakeResult:
    import warnings

    # The heavy libraries (trimesh and manifold3d, numba, pxr) load in _bake_locked,
    # inside the bake's stop handler: a stop while they load is this bake's stop
    # (interrupt.stop_behind), and importing this module stays cheap.
    warn = warn or (lambda msg: warnings.warn(msg, stacklevel=3))
    out = Path(out_path)
    if out.suffix not in (".usd", ".usdc", ".usda"):
        raise ExportError(f"{out}: unknown extension {out.suffix!r} (use .usd, .usdc or .usda)")
    if out.is_dir():
        raise ExportError(f"{out}: is a folder (give a file name ending in .usd, .usdc or "
                          f".usda)")
    check_threads(threads)
    check_writable(out.parent)
    check_output_names(out, scene_path)
    interrupt.check()
    lock = WorkLock(work_dir(out), out)
    lock.acquire()                  # a second bake to this output is refused here
    try:
        return _bake_locked(
            scene_path, out, device=device, layout=layout, frames=frames, threads=threads,
            cache=cache, progress=progress, warn=warn, force=force, resume=resume,
            chunk_frames=chunk_frames, checkpoint_seconds=checkpoint_seconds,
            checkpoints=checkpoints, simulation=simulation)
    finally:
        lock.release()


def _bake_locked(scene_path, out, *, device, layout, frames, threads, cache, progress, warn,
                 force, resume, chunk_frames, checkpoint_seconds, checkpoints,
                 simulation) -> BakeResult:
    from dempipe.pipeline.checkpoint import (CHECKPOINT_SECONDS, BakeStore, model_fingerprint,
                                             read_meta)
    from dempipe.pipeline.check import (behind_box_findings, behind_plane_findings,
                                        emission_finding, nothing_below_findings,
                                        sinking_finding, spin_finding, steps_finding)
    from dempipe.scene.build import build_model, initial_overlap_all_spheres
    from dempipe.scene.load import load_scene
    from dempipe.sim.simulator import BakeFailure, Simulator, resolve_device
    from dempipe.usd.chunks import write_usd_chunks
    from dempipe.usd.overlay import OverlayWriter
    from dempipe.usd.samples import ChunkSource

    from dempipe.usd.animation import LAYOUTS

    if layout not in LAYOUTS:       # before any work: the CLI's choice, for the API too
        raise ExportError(f"unknown USD layout {layout!r} (known: {', '.join(LAYOUTS)})")
    remove_stale_temporaries(out)
    if resume and (work_dir(out) / "meta.json").is_file():
        read_meta(work_dir(out))    # a damaged checkpoint: one line, before any work
    t_start = time.perf_counter()
    scene = with_simulation(load_scene(scene_path), simulation)
    if scene.usd is not None and _same_file(out, scene.usd.stage_path):
        raise ExportError(f"{out}: is the input stage {scene.usd.stage_path}; write the "
                          f"overlay to another file (e.g. {out.stem}_baked{out.suffix})")
    for msg in scene.usd.warnings if scene.usd is not None else ():
        warn(msg)
    device_asked = device or scene.simulation.device
    dev = resolve_device(device_asked)     # 'cuda' unusable: DeviceError; 'auto': quietly
    cache = cache if cache is not None else SphereCache()
    interrupt.check()
    model = build_model(scene, cache=cache, force=force)
    interrupt.check()
    start, end = parse_frame_range(frames, model.n_frames, model.first_frame)

    src = Path(scene_path).name

    check_run_time(model, src, scene)

    closing = expected_speeds(model)[1]
    for risk in (tunnelling(model, model.dt, closing,
                            "auto" if isinstance(scene.simulation.dt, str) else "given", src),
                 soft_contact(model, closing, src),
                 spin_finding(model, src, scene.simulation.dt),
                 steps_finding(model, src, scene.simulation.dt),
                 emission_finding(model, src),     # emitted bodies: known before they start
                 sinking_finding(model, src),
                 *behind_plane_findings(model, scene, src),
                 *behind_box_findings(model, scene, src),
                 *nothing_below_findings(model, scene, src)):
        if risk is not None and risk.level == ERROR and not force:
            raise StabilityError(f"{risk.message}. Fix: {risk.fix} (or bake with --force)")
        if risk is not None:
            warn(risk.message)

    store = BakeStore(out, model_fingerprint(model),
                      dict(device=dev, frames=f"{start}:{end}"), model.n_bodies,
                      chunk_frames=chunk_frames,
                      checkpoint_seconds=(CHECKPOINT_SECONDS if checkpoint_seconds is None
                                          else checkpoint_seconds))
    resuming = False
    if resume and store.exists():
        store.open()                       # CheckpointError if it does not fit
        # a bake killed before its first checkpoint left a folder with no State in it
        resuming = store.state_file is not None
        if not resuming:
            warn(f"the earlier bake to {out} stopped before its first checkpoint: baking "
                 f"from frame 0")
    elif resume:
        warn(f"no checkpoint of an earlier bake to {out} ({store.dir}): baking from frame 0")
    if not resuming:
        if store.exists() and not resume:
            warn(f"an interrupted bake to {out} left a checkpoint ({store.dir}); starting "
                 f"again from frame 0 replaces it (use --resume to go on from it)")
        overlap, body = initial_overlap_all_spheres(scene, model, cache=cache)
        if overlap > REFUSE_OVERLAP and not force:
            raise StabilityError(
                f"{src}: body {model.body_name(body)} overlaps another body or a collider by "
                f"{overlap:.0%} of the sphere diameter at frame 0; the first step would fling "
                f"it away. Space the bodies further apart (a randomly turned body swings about "
                f"its mesh origin) or move it clear of the colliders")
        if overlap > WARN_OVERLAP:
            warn(f"{src}: body {model.body_name(body)} starts {overlap:.0%} of a diameter deep "
                 f"in contact; it will be pushed out in the first steps")

        store.create()
    try:
        # the work folder exists from here: a stop says what it holds and how to go on
        interrupt.check()
        sim = Simulator(model, device=dev, threads=threads)
        state = model.initial_state()
        point = store.restore(sim, state) if resuming else None
    except interrupt.StopRequested as exc:
        raise _interrupted(exc, scene_path, out, store, None, 0, None) from None
    n_frames = end + 1

    def after_frame(k, st):
        if checkpoints and store.due():
            store.checkpoint(sim, st)
        elif store.buffer.full:
            store.keep_tail()             # frames to disk; the next checkpoint commits them

    failure = None
    if point is None or point.frames_done < n_frames:
        try:
            sim.run(state, n_frames, store.add, progress=progress, resume=point,
                    after_frame=after_frame)
            if checkpoints:
                store.checkpoint(sim, state)   # the last frames: a failed write keeps them
            else:
                store.keep_tail()
        except BakeFailure as exc:
            failure = exc
            store.keep_tail()
        except interrupt.StopRequested as exc:
            failure = exc
            if checkpoints and getattr(exc, "frames_done", None) is not None:
                store.checkpoint(sim, state)   # a finished step call: State and frames agree
            else:
                store.keep_tail()
        except KeyboardInterrupt as exc:       # not through our handlers: State unknown
            failure = exc
            store.keep_tail()
        except ExportError as exc:             # a chunk or checkpoint did not fit on disk
            # the last whole checkpoint is still the folder's (meta.json is replaced last)
            kept = (f"the checkpoint at frame {store.frames_done} in {store.dir} is kept: "
                    f"free the space, then run the same bake with --resume to go on from it"
                    if store.state_file else
                    "no checkpoint was written yet: free the space and bake again")
            raise ExportError(f"{exc}; {kept}") from None
    elif point is not None:
        sim.stats = point.stats

    report = dict(
        scene=str(scene_path), output=str(out), bodies=model.n_bodies, spheres=model.n_spheres,
        static_spheres=int(model.n_spheres - model.body_sphere_start[model.n_bodies]),
        diameter=model.diameter, dt=model.dt, steps_per_frame=model.steps_per_frame,
        steps=sim.stats.steps, frames=0, device=dev, threads=threads,
        wall_seconds=0.0, simulate_seconds=sim.stats.wall_seconds,
        seconds_per_step=(sim.stats.wall_seconds / (sim.stats.steps - sim.stats.steps_skipped)
                          if sim.stats.steps > sim.stats.steps_skipped else 0.0),
        steps_skipped_asleep=sim.stats.steps_skipped,
        # over the steps computed: a step skipped while every body slept costs nothing
        sphere_steps_per_second=(model.n_spheres * (sim.stats.steps - sim.stats.steps_skipped)
                                 / sim.stats.wall_seconds if sim.stats.wall_seconds else 0.0),
        max_overlap=sim.stats.max_overlap / model.diameter,
        # glue: the bonds, and how many broke in each frame (from the frame before)
        bonds=model.n_bonds,
        bonds_broken_per_frame=[b - a for a, b in zip([0] + sim.stats.bonds_broken,
                                                      sim.stats.bonds_broken)],
        sphere_build_seconds=model.build_info.get("sphere_build_seconds", 0.0),
        sphere_cache=[dict(shape=n, cache=c, seconds=s, spheres=k)
                      for n, c, s, k in model.build_info.get("shapes", [])],
        stiffness={n: k for n, k in model.stiffness_auto},
        export_seconds=0.0, layout=layout, completed=failure is None,
        resumed=resuming, resumed_from_frame=point.frames_done if point else None,
        checkpoints=store.checkpoints,
        checkpoint_seconds=store.checkpoint_seconds_spent,
    )
    kept = store.frames_kept()
    if kept <= start:                  # nothing to write
        if isinstance(failure, KeyboardInterrupt):
            raise _interrupted(failure, scene_path, out, store, None, 0, report)
        store.remove()
        if failure is not None:
            raise failure
        raise StabilityError(f"{src}: no frame in {frames} was reached")


    target = out if failure is None else partial_path(out)
    try:
        if scene.usd is not None:   # a USD stage in: an overlay over it out

            overlay = OverlayWriter(target, model, scene.usd)
            for block in ChunkSource(store.frame_chunks(), model.n_bodies, start).blocks():
                overlay.add(block)
            info = overlay.save()
        else:
            info = write_usd_chunks(target, store.frame_chunks(), model, layout=layout,
                                    start=start)
    except KeyboardInterrupt as exc:    # a stop while writing: the frames are on disk
        if failure is not None:
            raise
        raise _interrupted(exc, scene_path, out, store, None, 0, report) from None
    except ExportError as exc:
        # the frames are safe in the work folder: say so, and how to write them again
        raise ExportError(f"{write_failure(exc, target, store)}; the {kept} frames baked are "
                          f"kept in {store.dir}: free "
                          f"the space or fix the folder, then run the same bake with "
                          f"--resume to write them without simulating again") from None
    written = kept - start
    report.update(frames=written, export_seconds=info.seconds,
                  wall_seconds=time.perf_counter() - t_start, output=str(target))
    if failure is None:
        store.remove()
        # an earlier stopped bake's frames, now superseded by the whole file
        partial_path(out).unlink(missing_ok=True)
        return BakeResult(target, report)
    if isinstance(failure, KeyboardInterrupt):
        raise _interrupted(failure, scene_path, out, store, target, written, report)
    store.remove()          # a guard stopped it: resuming would stop there again
    exc = StabilityError(f"{failure} — {written} frames kept in {target}")
    exc.result = BakeResult(target, report, partial=True)
    raise exc


def write_failure(exc: ExportError, target: Path, store) -> str:
    """The message of a failed USD write, with the OS's reason where pxr hid it.

    pxr reports a full disk as C++ text ("Error in '...::WriteToFile' ... Could not
    close ..."), with the errno lost and its temporary file already removed. Its
    quoted reason is kept, and the free space of the folder is held against what the
    file needs (about 8 times the frames' bytes on disk, USD text being the larger
    form): below it, the reason is the full disk."""
    text = str(exc)
    if "pxrInternal" not in text and "Error in '" not in text:
        return text
    quoted = text.rsplit("'", 2)
    cause = quoted[-2] if len(quoted) == 3 else "USD could not write the layer"
    try:
        st = os.statvfs(_existing(target.parent))
        free = st.f_bavail * st.f_frsize
    except OSError:
        return f"{target}: cannot write USD file ({cause})"
    need = max(1 << 20, 8 * sum(p.stat().st_size for p, _, _ in store.frame_chunks()
                                if p.exists()))
    if free < need:
        return (f"{target}: cannot write USD file (No space left on device: "
                f"{free / 2**20:.1f} MiB free, the file needs about {need / 2**20:.1f} MiB)")
    return f"{target}: cannot write USD file ({cause})"


def _interrupted(failure, scene_path, out, store, target, written, report):
    """The BakeInterrupted for a stop: what was kept, and the command that resumes."""
    signum = getattr(failure, "signum", None)
    why = f"stopped by {signal_name(signum)}" if signum else "interrupted"
    if target is not None:
        kept = f"{written} frame{'s' * (written != 1)} kept in {target}"
    elif store.frames_kept():
        kept = f"while writing {out}; its {store.frames_kept()} frames are kept"
    else:
        kept = "no frame finished"
    if store.exists() and store.state_file:
        done = store.frames_done
        again = (f"; checkpoint at frame {done} in {store.dir}: resume with "
                 f"`dempipe bake {scene_path} -o {out} --resume`")
    else:       # stopped before the first checkpoint (a first bake's compile, say)
        again = (f"; no checkpoint yet: `dempipe bake {scene_path} -o {out}` starts it "
                 f"again")
    exc = BakeInterrupted(f"{why}; {kept}{again}")
    exc.exit_code = (128 + int(signum)) if isinstance(failure, StopRequested) else 130
    exc.result = BakeResult(target, report, partial=True) if target is not None else None
    return exc


class BakeInterrupted(DempipeError):
    """A stop signal or Ctrl-C during a bake; the frames done so far were written
    and the last checkpoint kept. exit_code: 128 + the signal's number."""

    exit_code = 130


def write_report(path, report: dict) -> None:
    """Write --report JSON atomically (checkpoint.atomic_write), creating its folder
    if it is missing (check_writable made sure, before the bake, that it can be)."""
    path = Path(path)
    text = json.dumps(report, indent=2, default=float).encode()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, lambda fh: fh.write(text))
    except OSError as exc:
        raise ExportError(f"{path}: cannot write the report ({exc.strerror or exc})") from None
