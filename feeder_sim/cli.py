"""``feeder-sim``: run scenes without ROS, writing the same MCAP topics as the node."""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path
import signal
import sys
import threading

from feeder_sim import __version__


class _StopSignals:
    """SIGINT and SIGTERM during ``feeder-sim run``. Until the first frame is recorded
    (loading, compiling: native code that holds Python's handlers off while it runs)
    nothing of the run exists, so the process ends at once, from a thread woken by the
    signal, and removes the log it had begun (``unfinished``). After, the run ends after the
    frame under way: the log is finalized, the summary and the plot cover the time
    simulated, and the exit status is 128 + the signal's number."""

    def __init__(self) -> None:
        self.received: int | None = None
        self.running = threading.Event()
        self.unfinished: Path | None = None

    def __enter__(self) -> _StopSignals:
        self._handlers = {sig: signal.signal(sig, self._handle)
                          for sig in (signal.SIGINT, signal.SIGTERM)}
        woken, self._marked = os.pipe()
        os.set_blocking(self._marked, False)
        self._wakeup = signal.set_wakeup_fd(self._marked, warn_on_full_buffer=False)
        threading.Thread(target=self._watch, args=(woken,), daemon=True).start()
        return self

    def __exit__(self, *exc) -> None:
        # the caller's handlers back (a test, a script calling main())
        signal.set_wakeup_fd(self._wakeup)
        for sig, handler in self._handlers.items():
            signal.signal(sig, handler)
        os.close(self._marked)     # the watcher reads the end of the pipe and leaves

    def _handle(self, signum: int, frame) -> None:
        self.received = signum

    def _watch(self, woken: int) -> None:
        with os.fdopen(woken, 'rb', buffering=0) as pipe:
            while data := pipe.read(1):
                if not self.running.is_set():
                    if self.unfinished is not None:
                        self.unfinished.unlink(missing_ok=True)
                    print(f'feeder-sim: stopped by {signal.Signals(data[0]).name} before the '
                          'first frame; nothing written', file=sys.stderr, flush=True)
                    os._exit(128 + data[0])

    def reason(self) -> str | None:
        return None if self.received is None else signal.Signals(self.received).name


def _output_file(option: str, value: str | None, kinds: tuple[str, ...] = ()) -> Path | None:
    """The file an option names, checked before the run (where it can be written, and its
    kind by suffix): a bad one is one line naming the option, not a failure after the run."""
    if not value:
        return None
    path = Path(value)
    if kinds and path.suffix.lower().lstrip('.') not in kinds:
        raise ValueError(f'{option} {value}: expected a file name ending in one of '
                         f'{", ".join("." + k for k in kinds)}')
    if path.is_dir():
        raise ValueError(f'{option} {value}: is a directory; give a file name in it')
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ValueError(f'{option} {value}: {parent} is a file, not a directory') from None
    except OSError as err:
        raise ValueError(f'{option} {value}: cannot create {parent} ({err.strerror})') from None
    if not os.access(parent, os.W_OK):
        raise ValueError(f'{option} {value}: {parent} is not writable')
    return path


def _plot_kinds() -> tuple[str, ...]:
    from matplotlib.backend_bases import FigureCanvasBase
    return tuple(FigureCanvasBase.get_supported_filetypes())


def _run(args: argparse.Namespace) -> int:
    with _StopSignals() as stops:
        return _run_until_stopped(args, stops)


def _run_until_stopped(args: argparse.Namespace, stops: _StopSignals) -> int:
    from feeder_sim.run import plot_trajectory, run, run_with_error_estimate, write_summary
    from feeder_sim.simulator import Simulator

    record = _output_file('--record', args.record)
    summary_path = _output_file('--summary', args.summary)
    plot = _output_file('--plot', args.plot, _plot_kinds()) if args.plot else (
        record.with_suffix('.png') if record else None)
    sim = Simulator(args.scene, method=args.method, time_step=args.time_step,
                    tolerance=args.tolerance, check_energy=args.check_energy)
    stops.unfinished = record
    result = (run_with_error_estimate if args.error_estimate else run)(
        sim, args.duration, publish_rate_hz=args.publish_rate, record=record,
        log_time=args.log_time, stop_reason=stops.reason,
        on_frame=lambda _: stops.running.set())
    if summary_path:
        write_summary(result.summary, summary_path)
    if plot:
        plot_trajectory(result.trajectory, plot, f'{sim.scene.name} ({sim.method})')
    s = result.summary
    if not (record or summary_path or plot):
        print('nothing written (add --record OUT.mcap for a log to replay, --summary OUT.json '
              'for these numbers)')
    print(f"{s['scene']}: {s['simulated_s']:.3f} s simulated in {s['wall_s']:.2f} s wall "
          f"({s['method']}, step {s['time_step_s']:g} s, {s['solver']['lcp_solves']} LCP solves, "
          f"{s['solver']['fallbacks']} fallbacks)")
    if 'time_step_auto' in s:
        a = s['time_step_auto']
        print(f"  time step auto: {a['time_step_s']:g} s ({a['steps_per_period']:.0f} steps per "
              f"drive period, fixed {a['fixed_steps_per_period']}), conveying speed within "
              f"{100 * a['estimated_relative_error']:.2g} % (tolerance "
              f"{100 * a['tolerance']:g} %); pilot {len(a['pilot']['candidates'])} runs of "
              f"{a['pilot']['simulated_s_each']:g} s, {a['pilot']['wall_s']:.2f} s wall")
    errors = s.get('numerical_error')
    part_errors = {p['name']: p for p in errors['parts']} if errors else {}
    for part in s['parts']:
        error = part_errors.get(part['name'], {}).get('mean_velocity_along_track_mps')
        print(f"  {part['name']}: mean speed along track "
              f"{1e3 * part['mean_velocity_along_track_mps']:.3f}"
              + ('' if error is None else f' ± {1e3 * error:.2g}') + ' mm/s')
    if errors:
        print(f"  numerical error (±, of the numbers above): {errors['method']}; "
              f"{errors['companion']['wall_s']:.2f} s wall more, "
              f"{errors['companion']['cost_ratio']:.2f}x the run")
        outcomes = errors.get('outcomes', {})
        o = s.get('outcomes', {})
        if o.get('exit_position_m') is not None:
            print(f"  parts exited {o['parts_exited']} ± {outcomes.get('parts_exited', 0):g}, "
                  f"feed rate {o['feed_rate_parts_per_min']:.3g} ± "
                  f"{outcomes.get('feed_rate_parts_per_min') or 0:.2g} per min")
        for line in errors['unresolved']:
            print(f'  numerical error: changes with the setting: {line}')
    for label, path in (('mcap', args.record), ('summary', args.summary), ('plot', plot)):
        if path:
            print(f'  {label}: {path}')
    if args.json:
        print(json.dumps(s, indent=2))
    if 'stopped' in s:
        print(f"feeder-sim: stopped by {s['stopped']['reason']} after {s['simulated_s']:.3f} of "
              f"{s['stopped']['planned_s']:g} s simulated; the files above hold that much",
              file=sys.stderr)
        return 128 + signal.Signals[s['stopped']['reason']].value
    return 0


def _compile(args: argparse.Namespace) -> int:
    import tempfile
    import time

    from feeder_sim.compiled.cache import key_dir
    from feeder_sim.compiled.jit import kernel_load_seconds
    from feeder_sim.model.scene import METHODS
    from feeder_sim.run import run
    from feeder_sim.simulator import Simulator

    for scene in args.scenes:
        for method in args.method or METHODS:
            t0, loading0 = time.perf_counter(), kernel_load_seconds()
            # a run as `run` and the node make it, frames recorded: their kernels too
            with tempfile.TemporaryDirectory() as scratch:
                run(Simulator(scene, method=method), args.duration,
                    record=Path(scratch) / 'frames.mcap')
            print(f'{scene} {method}: {kernel_load_seconds() - loading0:.1f} s compiling '
                  f'or loading kernels, {time.perf_counter() - t0:.1f} s in all', flush=True)
    print(f'cached in {key_dir()}')
    return 0


def _scenes(_: argparse.Namespace) -> int:
    from feeder_sim.model.scene import load_scene, scene_dirs, SceneError, shipped_scenes

    names = shipped_scenes()
    width = max((len(n) for n in names), default=0)
    for name in names:
        try:
            scene = load_scene(name)
            about = f'{scene.solver.method:<14} {scene.description or "(no description)"}'
        except SceneError as err:        # a scene file edited into an error: say so, go on
            about = f'{"-":<14} invalid: {err}'
        print(f'{name:<{width}}  {about}')
    print('(from ' + ', '.join(str(d) for d in scene_dirs()) + ')', file=sys.stderr)
    return 0


def _replay(args: argparse.Namespace) -> int:
    try:
        from feeder_sim.output.replay import DamagedLogError, replay
    except ImportError as err:  # rerun-sdk is the optional 'replay' extra
        raise NotImplementedError(
            f"replay needs rerun-sdk (pip install 'feeder_sim[replay]'): {err}") from err

    out = _output_file('--rrd', args.rrd)
    try:
        rrd = replay(args.log, out, spawn=args.spawn, allow_damaged=args.allow_damaged)
    except DamagedLogError as err:
        for line in err.lines:
            print(f'feeder-sim: damaged: {line}', file=sys.stderr)
        print('feeder-sim: nothing written; --allow-damaged replays the rest of the log',
              file=sys.stderr)
        return 1
    print(rrd)
    print(f'  open it with: rerun {rrd}')
    return 0


def _paper(args: argparse.Namespace) -> int:
    from feeder_sim.reports.paper import FIGURES, paper

    figures = args.only.split(',') if args.only else FIGURES
    results = paper(args.out, figures)
    for name in results:
        print(f'  {name}: written to {args.out}')
    print(f'  numbers: {Path(args.out) / "paper.json"}')
    return 0


def _study(args: argparse.Namespace) -> int:
    from feeder_sim.studies import run_study

    if args.workers is not None and args.workers < 1:
        raise ValueError(f'--workers must be at least 1, got {args.workers}')
    summary = run_study(args.study, args.out, scheduler=args.scheduler, workers=args.workers,
                        recompute=args.recompute)
    best = summary['best_design']
    print(f"{summary['trials']} trials ({summary['failed']} failed) of {len(summary['designs'])} "
          f"designs in {args.out}")
    if best is not None:
        d = summary['designs'][[e['design'] for e in summary['designs']].index(best)]
        m = d['metrics'][summary['objective']['metric']]
        error = m.get('numerical_error')
        print(f"  best design {best}: {d['parameters']}, {summary['objective']['metric']} = "
              f"{m['mean']:.6g} (95 % interval {m['ci95'][0]:.6g} .. {m['ci95'][1]:.6g}"
              + ('' if error is None else f', numerical error ± {error:.3g}') + ')')
    if 'convergence' in summary:
        c = summary['convergence']
        print(f"  numerical error on {c['designs_measured']} designs ({c['method']}), "
              f"{c['cost_ratio']:.2f}x the trials' time; {len(summary['warnings'])} design "
              'metrics with an error beyond their interval (study.json: warnings)')
    if summary['failed']:
        # a study with failed trials is not a clean result: scripts must see it
        first = summary.get('first_error') or 'see results.csv, column error'
        print(f"feeder-sim: error: {summary['failed']} of {summary['trials']} trials failed; "
              f'the first: {first}', file=sys.stderr)
        return 1
    return 0


def _split(text: str | None) -> list[str] | None:
    return [x.strip() for x in text.split(',') if x.strip()] if text else None


def _accuracy(args: argparse.Namespace) -> int:
    from feeder_sim.reports.accuracy import CASES, run_accuracy

    if args.list:
        for key, case in CASES.items():
            print(f'{key}: {case.description}; {case.quantity}')
        return 0
    result = run_accuracy(args.out, cases=_split(args.cases), methods=_split(args.methods),
                          quick=args.quick, repeats=args.repeats,
                          progress=None if args.quiet else print)
    for line in result['misses']:
        print(f'  MISSED: {line}', file=sys.stderr)
    return 1 if result['misses'] else 0


def _stability(args: argparse.Namespace) -> int:
    from feeder_sim.reports.stability import run_stability, SCENES

    if args.list:
        for key, case in SCENES.items():
            print(f'{key}: {case.description}')
        return 0
    kw = {'methods': _split(args.methods)} if args.methods else {}
    result = run_stability(args.out, cases=_split(args.cases),
                           progress=None if args.quiet else print, **kw)
    if args.quiet:      # otherwise the report's own last line said it
        print(f'stability: {"PASSED" if result["passed"] else "FAILED"} '
              f'({Path(args.out) / "stability.json"})')
    return 0 if result['passed'] else 1


def _node(args: argparse.Namespace) -> int:
    from feeder_sim.ros.client import run

    return run(args)


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (it prints the whole usage before them)."""

    def error(self, message: str):
        self.exit(2, f'{self.prog}: error: {message} (see {self.prog} -h)\n')


def build_parser() -> argparse.ArgumentParser:
    from feeder_sim.model.scene import METHODS

    parser = _Parser(prog='feeder-sim', description=__doc__)
    parser.add_argument('--version', action='version', version=f'feeder_sim {__version__}')
    parser.add_argument('-q', '--quiet', action='store_true', help='no progress lines')
    sub = parser.add_subparsers(dest='verb', required=True)

    p = sub.add_parser('run', help='run a scene and record it')
    p.add_argument('scene', help='scene file (.yaml) or the name of a shipped scene')
    p.add_argument('--duration', type=float, required=True, help='simulated seconds')
    p.add_argument('--record', metavar='OUT.mcap', help='write an MCAP log')
    p.add_argument('--log-time', choices=('wall', 'sim'), default='wall',
                   help="MCAP log times: 'wall' (the run's start plus the simulated time, so "
                        "viewers show dates; default) or 'sim' (simulated time alone: the same "
                        'run gives the same file)')
    p.add_argument('--summary', metavar='OUT.json', help='write the run summary')
    p.add_argument('--plot', metavar='OUT.png',
                   help='position along the track vs time (default: next to --record)')
    p.add_argument('--publish-rate', type=float, default=100.0, metavar='HZ',
                   help='frames per simulated second recorded (default 100)')
    p.add_argument('--method', choices=METHODS,
                   help="override the scene's solver.method")
    p.add_argument('--time-step', type=float, help="override the scene's solver.time_step")
    p.add_argument('--tolerance', type=float, help="override the scene's solver.tolerance")
    p.add_argument('--json', action='store_true', help='also print the summary as JSON')
    p.add_argument('--error-estimate', action='store_true',
                   help='run the scene again at a refined setting (half the step; '
                        "event_driven: the tolerance / 100) and add each outcome's numerical "
                        'error to the summary (numerical_error)')
    p.add_argument('--check-energy', type=float, metavar='TOL',
                   help='debug: stop with an error when the mechanical energy rises by more '
                        'than TOL of the energy scale over a step or event without drive '
                        'work (also $FEEDER_SIM_CHECK_ENERGY)')
    p.set_defaults(func=_run)

    p = sub.add_parser('replay', help='convert an MCAP log to a rerun recording (.rrd)')
    p.add_argument('log', metavar='LOG.mcap', help='log written by feeder-sim run or the node')
    p.add_argument('--rrd', metavar='OUT.rrd', help='output (default: next to the log)')
    viewer = p.add_mutually_exclusive_group()
    viewer.add_argument('--viewer', dest='spawn', action='store_const', const=True,
                        help='open the rerun viewer on the recording')
    viewer.add_argument('--no-viewer', dest='spawn', action='store_const', const=False,
                        help='only write the file (default: open the viewer if there is a '
                             'display)')
    p.add_argument('--allow-damaged', action='store_true',
                   help='replay a damaged log (chunks failing their CRC) without the frames it '
                        'lost, each lost time range a warning (default: exit 1 naming them)')
    p.set_defaults(func=_replay, spawn=None)

    p = sub.add_parser('paper', help="regenerate the paper's figures (PNG + JSON)")
    p.add_argument('--out', default='out/paper', help='output folder (default out/paper)')
    p.add_argument('--only', metavar='FIGS',
                   help='comma-separated subset of fig7,flip,fig8,fig9,fig10')
    p.set_defaults(func=_paper)

    p = sub.add_parser('accuracy', help='error against run time of every method on cases with '
                                        'an exact reference (plot, table, JSON)')
    p.add_argument('--out', default='out/accuracy', help='output folder (default out/accuracy)')
    p.add_argument('--cases', metavar='KEYS', help='comma-separated case keys (default: all; '
                                                    'see --list)')
    p.add_argument('--methods', metavar='NAMES',
                   help='comma-separated subset of time_stepping,event_driven,impulse_based,'
                        'pymunk (default: all; pymunk when installed)')
    p.add_argument('--quick', action='store_true',
                   help='only the coarsest and the finest setting of each method')
    p.add_argument('--repeats', type=int, default=1,
                   help='time each point this often, keep the median (default 1)')
    p.add_argument('--list', action='store_true', help='list the cases and exit')
    p.set_defaults(func=_accuracy)

    p = sub.add_parser('stability', help='stiff and extreme scenes on every method; exits 1 '
                                         'when a criterion is missed (table PNG + JSON)')
    p.add_argument('--out', default='out/stability', help='output folder (default '
                                                          'out/stability)')
    p.add_argument('--cases', metavar='KEYS', help='comma-separated scene keys (default: all; '
                                                    'see --list)')
    p.add_argument('--methods', metavar='NAMES', help='comma-separated subset of the methods')
    p.add_argument('--list', action='store_true', help='list the scenes and exit')
    p.set_defaults(func=_stability)

    p = sub.add_parser('study', help='a design study: trials on Dask, statistics, plots')
    p.add_argument('study', help='study file (.yaml)')
    p.add_argument('--out', required=True, help='output folder; run again to complete it')
    p.add_argument('--scheduler', metavar='ADDRESS',
                   help='a Dask scheduler, e.g. tcp://HOST:8786 (default: a local cluster)')
    p.add_argument('--workers', type=int, metavar='N',
                   help='local cluster size (default: one process per core)')
    p.add_argument('--recompute', action='store_true',
                   help='--out holds trials of another spec (a changed duration, scene, '
                        'perturbation or feeder_sim version): compute them all again instead '
                        'of refusing')
    p.set_defaults(func=_study)

    p = sub.add_parser('compile', help='compile the kernels scenes need, ahead of their first '
                                       'run (a container build, a robot before a shift)')
    p.add_argument('scenes', nargs='*', default=['track_one_box'],
                   help='scene files or shipped scene names (default: the default scene)')
    p.add_argument('--method', choices=METHODS, action='append',
                   help='a stepping method (repeatable; default: all)')
    p.add_argument('--duration', type=float, default=0.05,
                   help='simulated s run on each (default 0.05); a kernel only a rarer event '
                        'needs compiles when first met')
    p.set_defaults(func=_compile)

    p = sub.add_parser('scenes', help='list the shipped scenes')
    p.set_defaults(func=_scenes)

    p = sub.add_parser('node', help='talk to a running feeder_sim node (no ros2 CLI needed)')
    common = argparse.ArgumentParser(add_help=False)
    # before or after the subcommand; a subcommand's default would override the one before it
    for q, default in ((p, None), (common, argparse.SUPPRESS)):
        q.add_argument('--node', default=default or '/feeder_sim', metavar='/NAMESPACE/NAME',
                       help='the node (default /feeder_sim)')
        q.add_argument('--timeout', type=float, default=default or 5.0, metavar='S',
                       help='wall s to wait for the node, for each answer and each message '
                            '(default 5); exit 2 after')
    cmd = p.add_subparsers(dest='command', required=True, metavar='SUBCOMMAND')
    c = cmd.add_parser('vibration', parents=[common], help='command the drive (vibration_cmd)')
    c.add_argument('amplitude', type=float, metavar='AMPLITUDE_M')
    c.add_argument('frequency', type=float, metavar='FREQUENCY_HZ')
    c.add_argument('--topic', help="the node's command topic (default: found in the graph)")
    for verb, text in (('pause', 'pause the simulation'), ('resume', 'resume it'),
                       ('step', 'advance a paused node steps_per_call frames'),
                       ('reset', "back to the scene's start, t = 0"),
                       ('list', 'the parts now, one per line')):
        cmd.add_parser(verb, parents=[common], help=text)
    c = cmd.add_parser('spawn', parents=[common], help='add a part; prints the name it got')
    c.add_argument('template', help="the scene's dynamic body to copy, e.g. box")
    c.add_argument('--name', help='its name (default: the node picks a free one)')
    c.add_argument('--pose', nargs=3, type=float, metavar=('X', 'Y', 'YAW'),
                   help='body frame pose in the world frame: m, m, rad')
    c.add_argument('--allow-renaming', action='store_true', help='a taken --name gets a suffix')
    cmd.add_parser('delete', parents=[common], help='remove a part').add_argument('name')
    c = cmd.add_parser('param', parents=[common], help="set a parameter (as its current type)")
    c.add_argument('name')
    c.add_argument('value')
    c = cmd.add_parser('echo', parents=[common], help='print part poses (name x y yaw) or a '
                                                      "sensor's messages")
    c.add_argument('what', choices=('poses', 'sensor'))
    c.add_argument('name', nargs='?', help='the sensor (echo sensor NAME)')
    c.add_argument('--count', type=int, default=1, metavar='K', help='messages (default 1)')
    p.set_defaults(func=_node)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format='[feeder_sim] %(message)s')
    try:
        return args.func(args)
    except (ValueError, OSError, NotImplementedError) as err:
        # Bad input is the user's to fix: one clear line, no traceback.
        print(f'feeder-sim: error: {err}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
