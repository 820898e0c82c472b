"""`d3rqn-log`: record a run's messages into an MCAP log, and inspect, play back, export, plot or recover logs.

    d3rqn-log record --config runs/R/config.toml --transport.mode client --transport.connect tcp/127.0.0.1:7447
    d3rqn-log info runs/R/traffic.mcap
    d3rqn-log play runs/R/traffic.mcap --keys episodes --to-run offline --speed 0 --transport.connect ...
    d3rqn-log export runs/R/traffic.mcap --csv runs/R/export --images runs/R/view.mcap
    d3rqn-log export runs/R/traffic.mcap --tensorboard runs/R/tensorboard-export
    d3rqn-log plot runs/R/traffic.mcap --output runs/R/training.png --x env_steps
    d3rqn-log recover runs/R/traffic.mcap runs/R/traffic-recovered.mcap

info, export and plot also read the log of a run still in progress (or of a killed recorder)
up to the recorder's last flush. A bad or unwritable file gives one line on stderr and exit
code 1; a bad config value, exit code 2.
"""

from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path

from common.config_cli import add_config_arguments, parse_config_or_exit, parse_flags

PROG = "d3rqn-log"
AXES = ("env_steps", "episodes")  # plot --x: the fields of replay.recorder.scalars.Point


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    record = commands.add_parser("record", help="record a run's messages until stopped (SIGINT/SIGTERM)",
                                 description="Subscribes to <namespace>/<run>/** and writes every message into one "
                                             "MCAP file (record.* settings: weights sampling, flushes, views).")
    record.add_argument("--output", type=Path, default=None,
                        help="log file (default: <run.runs_dir>/<run.name>/traffic.mcap; an existing file is never "
                             "overwritten: -2, -3, ... is added to the name)")
    record.add_argument("--tensorboard", type=Path, default=None, metavar="DIR",
                        help="also write the run's curves as TensorBoard event files into DIR while recording "
                             "(a new file beside any there: TensorBoard shows them as one run)")
    add_config_arguments(record)
    record.set_defaults(handler=_record)

    info = commands.add_parser("info", help="channels, message counts, time span, episodes, size")
    info.add_argument("log", type=Path)
    info.set_defaults(handler=_info)

    play = commands.add_parser("play", help="publish a log's messages on Zenoh again",
                               description="Re-publishes the recorded wire messages, byte for byte, in log-time "
                                           "order. Only --transport.* (and the namespace) of the config are used.")
    play.add_argument("log", type=Path)
    play.add_argument("--to-run", default=None, help="publish under this run name (default: the recorded run)")
    play.add_argument("--keys", default=None, metavar="PATTERN,...",
                      help="only keys matching these key expressions, relative to the run (e.g. episodes,metrics/**)")
    play.add_argument("--speed", type=float, default=1.0, help="1 = recorded speed, 2 = twice as fast, 0 = as fast "
                                                                "as possible (default 1)")
    play.add_argument("--wait-s", type=float, default=5.0,
                      help="how long to wait for subscribers before playing (default 5)")
    add_config_arguments(play)
    play.set_defaults(handler=_play)

    export = commands.add_parser("export", help="metrics and episode records to CSV; camera frames for Foxglove; "
                                                "curves for TensorBoard")
    export.add_argument("log", type=Path)
    export.add_argument("--csv", type=Path, default=None, metavar="DIR",
                        help="directory for the CSV tables (default: <log folder>/export unless --images or "
                             "--tensorboard is given)")
    export.add_argument("--images", type=Path, default=None, metavar="FILE.mcap",
                        help="write a Foxglove viewing file: camera frames, steps and metrics as JSON")
    export.add_argument("--image-format", choices=("png", "jpeg"), default="png")
    export.add_argument("--tensorboard", type=Path, default=None, metavar="DIR",
                        help="write the curves as TensorBoard event files into DIR, which must hold none yet "
                             "(`tensorboard --logdir DIR`)")
    export.set_defaults(handler=_export)

    plot = commands.add_parser("plot", help="training curves to a PNG")
    plot.add_argument("log", type=Path)
    plot.add_argument("--output", type=Path, default=None, help="PNG file (default: <log folder>/training.png)")
    plot.add_argument("--title", default=None, help="figure title (default: run name, strategy, replay capacity)")
    plot.add_argument("--x", choices=AXES, default=None,
                      help="draw every panel against env steps or episodes (default: the paper's axes: return "
                           "against episodes, epsilon against env steps, loss against updates); a dashed line "
                           "marks the start of updates")
    plot.set_defaults(handler=_plot)

    recover = commands.add_parser("recover", help="rewrite a cut-short log into a complete, indexed one")
    recover.add_argument("log", type=Path)
    recover.add_argument("output", type=Path)
    recover.set_defaults(handler=_recover)
    return parser


def main(argv: list[str] | None = None) -> int:
    from replay.recorder.reader import LogError  # imported here so `--help` stays fast

    parser = build_parser()
    args = parse_flags(parser, argv)
    config = None
    if hasattr(args, "preset"):  # record and play talk to a run over Zenoh
        args, config = parse_config_or_exit(parser, argv)
    try:
        return args.handler(args, config) or 0
    except (LogError, OSError) as error:  # a bad log, or a file that cannot be written
        print(f"{PROG} {args.command}: {error}", file=sys.stderr)
        return 1


def _record(args, config) -> int:
    from replay.recorder.recorder import run_recorder
    return run_recorder(config, args.output, args.tensorboard)


def _info(args, config) -> None:
    from common.wire.messages import EpisodeRecord
    from replay.recorder.reader import LogFile
    from replay.recorder.arrival import peek

    with LogFile(args.log, unfinished_ok=True) as log:
        keys = log.keys()
        start, end = log.time_span_ns
        counts = log.message_counts
        records = [message for _, message in log.messages(EpisodeRecord)]
        weights = [topic for topic in log.wire_topics() if topic == keys.weights]
        versions = [peek(record.data).version for record in log.records(weights)] if weights else []
        steps = sum(record.length for record in records)
        mean_return = sum(record.episode_return for record in records) / len(records) if records else float("nan")
        chunks = len(log.summary.chunk_indexes)
        print(f"file       {log.path}: {log.size_bytes / 2**20:.2f} MB ({log.size_bytes:,d} bytes), {chunks} chunks"
              + ("" if log.finished else "; unfinished (still recording, or the recorder was killed): read up "
                                         "to its last flush"))
        print(f"run        {keys.root}")
        print(f"time span  {_clock(start)} to {_clock(end)} UTC ({(end - start) / 1e9:.1f} s)")
        print(f"messages   {sum(counts.values()):,d} in {len(counts)} channels")
        print(f"episodes   {counts.get(keys.episodes, 0):,d} recorded; {len(records):,d} records, "
              f"{steps:,d} env steps, mean return {mean_return:.2f}")
        print(f"weights    versions {', '.join(map(str, versions)) or 'none'}")
        counters = log.recorder_counters()
        print("recorder   " + (", ".join(f"{name} {value}" for name, value in counters.items())
                               or "no final counters (the recorder did not close this file)"))
        print("channels")
        for channel in sorted(log.channels.values(), key=lambda c: c.topic):
            kind = channel.metadata.get("message_type") or "view"
            print(f"  {counts.get(channel.topic, 0):>8,d}  {channel.message_encoding:<7}  {kind:<16}  {channel.topic}")


def _clock(ns: int) -> str:
    return datetime.datetime.fromtimestamp(ns / 1e9, datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


def _play(args, config) -> None:
    from common.transport import open_session
    from common.keys import Keys
    from replay.recorder.play import play
    from replay.recorder.reader import LogFile

    patterns = [part.strip() for part in args.keys.split(",") if part.strip()] if args.keys else None
    with LogFile(args.log) as log:
        target = Keys(config.transport.namespace, args.to_run or log.keys().run)
        with open_session(config.transport) as session:
            report = play(log, session, target, patterns, args.speed, args.wait_s)
    for key in report.unmatched:
        print(f"no subscriber for {key} when playing started; its first messages may be lost", file=sys.stderr)
    total = sum(report.published.values())
    print(f"published {total:,d} messages on {len(report.published)} keys under {target.root} "
          f"in {report.seconds:.1f} s")
    for key, count in sorted(report.published.items()):
        print(f"  {count:>8,d}  {key}")


def _export(args, config) -> None:
    from replay.recorder.export import export_csv, export_images
    from replay.recorder.reader import LogFile
    from replay.recorder.tensorboard_events import export_tensorboard

    with LogFile(args.log, unfinished_ok=True) as log:
        if args.csv is not None or args.images is None and args.tensorboard is None:
            for path in export_csv(log, args.csv or args.log.parent / "export"):
                print(f"wrote {path}")
        if args.images is not None:
            count = export_images(log, args.images, args.image_format)
            print(f"wrote {args.images}: {count:,d} view messages")
        if args.tensorboard is not None:
            count = export_tensorboard(log, args.tensorboard)
            print(f"wrote {args.tensorboard}: {count:,d} scalar points (tensorboard --logdir {args.tensorboard})")


def _plot(args, config) -> None:
    from replay.recorder.plot import PLOTTED, plot_training
    from replay.recorder.reader import LogFile
    from replay.recorder.scalars import read_series

    output = args.output or args.log.parent / "training.png"
    with LogFile(args.log, unfinished_ok=True) as log:
        config = log.config()
        title = args.title or (f"run {config.run.name}: {config.exploration.strategy}, "
                               f"replay capacity {config.replay.capacity}")
        plot_training(read_series(log, PLOTTED), output, title, args.x)
    print(f"wrote {output}")


def _recover(args, config) -> None:
    from replay.recorder.recover import recover

    result = recover(args.log, args.output)
    lost = result.source_bytes - result.bytes_read
    print(f"wrote {args.output}: {result.messages:,d} messages on {result.channels} channels, "
          f"{result.metadata} metadata records; {lost:,d} bytes of a cut-off record dropped, "
          f"{result.chunks_skipped} damaged chunks and {result.messages_orphaned} orphaned messages skipped"
          + (f"; stopped early at damage: {result.damage}" if result.damage else ""))


if __name__ == "__main__":
    from common.shell import run_main  # here: reading a log needs no Zenoh
    run_main(main)
