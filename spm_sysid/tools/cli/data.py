"""Commands about data: ``make-bag`` (a data file as a rosbag2 bag) and ``fetch-data``."""

from __future__ import annotations

import math

import numpy as np

from .common import UserError, comma_list

__all__ = ["add_parsers"]


def cmd_make_bag(args) -> int:
    from ...core.io.bagio import write_io_bag
    from ...core.record import DataSpec, load_record

    # everything is checked before anything is read or touched
    if not (args.rate > 0 and math.isfinite(args.rate)):
        raise UserError(f"--rate must be a positive number of Hz, got {args.rate}")
    if not (args.start >= 0 and math.isfinite(args.start) and args.start < 4e9):
        raise UserError(f"--start must be a time in seconds, 0 <= start < 4e9, got {args.start}")
    spec = DataSpec.from_values({"inputs": args.inputs, "output": args.output_column},
                                data=args.data)
    record = load_record(spec)
    info = record.segment_info()
    if record.rejected or info.gaps or len(info.bounds) > 1:
        raise UserError(f"{record.source}: {record.rejected} row(s) with NaN/inf and "
                        f"{info.gaps} gap(s); a bag replays every sample at a fixed rate, so "
                        "clean the file first")
    u, y = record.u, record.y
    names = record.input_names if record.n_inputs > 1 else None
    outs = record.output_names if record.n_outputs > 1 else None
    out_topics = [t for t in args.output_topic.split(",") if t.strip()]
    path = write_io_bag(args.output, u, y, rate_hz=args.rate, start_ns=int(args.start * 1e9),
                        input_topic=args.input_topic, output_topic=args.output_topic,
                        input_frame=args.input_frame, output_frame=args.output_frame,
                        input_names=names, overwrite=args.force, output_names=outs)
    kinds = []
    if np.ndim(u) == 2:
        kinds.append(f"{u.shape[1]} inputs as sensor_msgs/msg/JointState effort[0.."
                     f"{u.shape[1] - 1}] ({', '.join(names or [])})")
    if outs and len(out_topics) == 1:
        kinds.append(f"{len(outs)} outputs as sensor_msgs/msg/JointState velocity[0.."
                     f"{len(outs) - 1}] ({', '.join(outs)}); read them with --output-field "
                     + ",".join(f"velocity[{i}]" for i in range(len(outs)))
                     + f" --output-names {','.join(outs)}")
    elif outs:
        kinds.append(f"{len(outs)} outputs, one geometry_msgs/msg/AccelStamped topic each; "
                     f"read them with --output-names {','.join(outs)}")
    print(f"wrote {len(u)} samples per topic at {args.rate:g} Hz to {path} "
          f"({args.input_topic}, {args.output_topic}){'; ' + '; '.join(kinds) if kinds else ''}")
    return 0


def cmd_fetch_data(args) -> int:
    from ...core.io.datasets import DAISY_ROBOT_ARM_URL, download_robot_arm

    path = download_robot_arm(url=args.url or DAISY_ROBOT_ARM_URL, dest=args.output)
    print(f"robot-arm data verified and saved to {path}")
    return 0


def add_parsers(sub) -> None:
    """Register ``make-bag`` and ``fetch-data``."""
    p = sub.add_parser("make-bag", help="write u, y data as a rosbag2 MCAP bag")
    p.add_argument("--data", metavar="PATH",
                   help="two-column, CSV or MATLAB (.mat) file (default: robot arm)")
    p.add_argument("--output", metavar="PATH", default="bags/robot_arm",
                   help="bag directory to create (default bags/robot_arm)")
    p.add_argument("--rate", type=float, default=100.0,
                   help="nominal sample rate in Hz (default 100: the data gives none)")
    p.add_argument("--start", type=float, default=0.0, help="first stamp, seconds")
    p.add_argument("--inputs", metavar="NAMES", type=comma_list,
                   help="input columns of --data (several: written as JointState efforts)")
    p.add_argument("--output-column", dest="output_column", metavar="NAME",
                   help="output column of --data (with --inputs; default 'y', else the last)")
    p.add_argument("--input-topic", default="/robot_arm/torque")
    p.add_argument("--output-topic", default="/robot_arm/acceleration")
    p.add_argument("--input-frame", default="robot_arm_base")
    p.add_argument("--output-frame", default="robot_arm_tip")
    p.add_argument("--force", action="store_true",
                   help="replace an existing bag (only a bag; a directory holding other "
                        "files is refused)")
    p.set_defaults(func=cmd_make_bag)

    p = sub.add_parser("fetch-data", help="download the robot-arm data into the user cache")
    p.add_argument("--url", help="alternative download address")
    p.add_argument("--output", metavar="PATH", help="where to save (default: user cache)")
    p.set_defaults(func=cmd_fetch_data)
