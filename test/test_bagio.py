"""Robot-arm bags: written with rosbags, read back with rosbags and with mcap."""

import subprocess
import sys

import numpy as np
import pytest
import yaml

from spm_sysid.core.errors import BagError, DataError
from spm_sysid.core.io.bagio import read_bag_signals, write_io_bag
from spm_sysid.core.stream.buffer import pair_streams

from .conftest import ROOT


def test_metadata_declares_version_9_mcap_and_both_topics(arm_bag):
    meta = yaml.safe_load((arm_bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    assert meta["message_count"] == 2048
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert topics["/robot_arm/torque"]["topic_metadata"]["type"] == \
        "geometry_msgs/msg/WrenchStamped"
    assert topics["/robot_arm/acceleration"]["topic_metadata"]["type"] == \
        "geometry_msgs/msg/AccelStamped"
    for t in topics.values():
        assert t["message_count"] == 1024
        qos = t["topic_metadata"]["offered_qos_profiles"][0]
        assert qos["reliability"] == "reliable" and qos["durability"] == "volatile"
    assert [f["path"] for f in meta["files"]] == ["robot_arm.mcap"]


def test_round_trip_with_rosbags(arm_bag, robot_arm):
    u, y = robot_arm
    sig = read_bag_signals(arm_bag)
    assert sig.input_count == sig.output_count == 1024 and sig.unpaired == 0
    assert np.array_equal(sig.u, u) and np.array_equal(sig.y, y)
    assert np.array_equal(sig.stamps_ns, np.arange(1024) * 10_000_000)  # 100 Hz nominal
    # reading the .mcap file directly works too
    assert np.array_equal(read_bag_signals(arm_bag / "robot_arm.mcap").y, y)


def test_round_trip_with_the_mcap_library(arm_bag, robot_arm):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    u, y = robot_arm
    got = {"/robot_arm/torque": [], "/robot_arm/acceleration": []}
    stamps = {k: [] for k in got}
    log_times = {k: [] for k in got}
    with open(arm_bag / "robot_arm.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages():
            got[channel.topic].append(
                msg.wrench.torque.z if schema.name == "geometry_msgs/msg/WrenchStamped"
                else msg.accel.linear.x)
            stamps[channel.topic].append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
            log_times[channel.topic].append(message.log_time)
    assert np.array_equal(got["/robot_arm/torque"], u)
    assert np.array_equal(got["/robot_arm/acceleration"], y)
    assert stamps["/robot_arm/torque"] == stamps["/robot_arm/acceleration"]
    assert np.all(np.diff(stamps["/robot_arm/torque"]) == 10_000_000)
    assert log_times["/robot_arm/torque"] == stamps["/robot_arm/torque"]


def test_options_rate_topics_and_overwrite(tmp_path):
    u, y = np.arange(5.0), -np.arange(5.0)
    p = write_io_bag(tmp_path / "b", u, y, rate_hz=250, start_ns=10**9,
                     input_topic="/a/effort", output_topic="/a/acc")
    sig = read_bag_signals(p, input_topic="/a/effort", output_topic="/a/acc")
    assert sig.stamps_ns.tolist() == [10**9 + k * 4_000_000 for k in range(5)]
    with pytest.raises(BagError, match="already exists"):
        write_io_bag(p, u, y)
    write_io_bag(p, u[:3], y[:3], overwrite=True)
    assert read_bag_signals(p).input_count == 3
    with pytest.raises(BagError, match="rate"):
        write_io_bag(tmp_path / "c", u, y, rate_hz=0)
    with pytest.raises(BagError, match="finite"):
        write_io_bag(tmp_path / "d", np.array([1.0, np.nan]), np.zeros(2))


def test_pairing_by_stamp_with_tolerance():
    # one pairing rule, offline and in the node (the values are the sample indices)
    def pairs(tu, ty, tol):
        events = sorted([("u", t, float(i)) for i, t in enumerate(tu)]
                        + [("y", t, float(i)) for i, t in enumerate(ty)], key=lambda e: e[1])
        _, u, y, _ = pair_streams(events, tol)
        return u.tolist(), y.tolist()

    iu, iy = pairs([0, 10, 20, 30], [1, 21, 50], 2)
    assert iu == [0, 2] and iy == [0, 1]
    iu, iy = pairs([0, 10], [0, 10], 0)
    assert iu == [0, 1]


def _spm(*args):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_make_bag_and_identify_from_bag_via_cli(tmp_path):
    out = tmp_path / "arm"
    r = _spm("make-bag", "--output", str(out), "--rate", "50")
    assert r.returncode == 0, r.stderr
    assert (out / "metadata.yaml").exists() and (out / "arm.mcap").exists()
    r = _spm("make-bag", "--output", str(out))
    assert r.returncode == 2 and "already exists" in r.stderr
    r = _spm("identify", "--bag", str(out), "--seed", "1", "--validation", "none")
    assert r.returncode == 0, r.stderr
    assert "AIC = -10744.78" in r.stdout and "1024 samples" in r.stdout


@pytest.fixture
def broken(tmp_path, arm_bag):
    """Damaged copies of the robot-arm bag."""
    import shutil

    def copy(name):
        dst = tmp_path / name
        shutil.copytree(arm_bag, dst)
        return dst

    return copy


def test_error_missing_path_and_not_a_bag(tmp_path):
    with pytest.raises(BagError, match="bag not found"):
        read_bag_signals(tmp_path / "nothing")
    (tmp_path / "dir").mkdir()
    with pytest.raises(BagError, match="no metadata.yaml"):
        read_bag_signals(tmp_path / "dir")
    f = tmp_path / "data.txt"
    f.write_text("1 2\n")
    with pytest.raises(BagError, match="not a bag"):
        read_bag_signals(f)


def test_error_corrupt_and_truncated_mcap(broken):
    trunc = broken("trunc")
    mcap = next(trunc.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="cannot read"):
        read_bag_signals(trunc)
    garbage = broken("garbage")
    mcap = next(garbage.glob("*.mcap"))
    mcap.write_bytes(b"this is not an mcap file at all" * 10)
    with pytest.raises(BagError, match="cannot read"):
        read_bag_signals(garbage)


def test_error_missing_topic_and_unexpected_type(arm_bag):
    with pytest.raises(BagError, match="has no topic /robot_arm/effort; it has"):
        read_bag_signals(arm_bag, input_topic="/robot_arm/effort")
    # both topics swapped: the AccelStamped topic has no wrench field
    with pytest.raises(BagError, match="AccelStamped.*does not exist"):
        read_bag_signals(arm_bag, input_topic="/robot_arm/acceleration",
                         output_topic="/robot_arm/torque", input_field="wrench.torque.z")
    with pytest.raises(BagError, match="malformed field path"):
        read_bag_signals(arm_bag, input_field="wrench..z")


def test_error_topic_of_a_type_without_a_number(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer

    from spm_sysid.core.io.bagio import typestore

    store = typestore()
    String = store.types["std_msgs/msg/String"]
    path = tmp_path / "strings"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        for topic in ("/robot_arm/torque", "/robot_arm/acceleration"):
            c = w.add_connection(topic, "std_msgs/msg/String", typestore=store)
            w.write(c, 0, store.serialize_cdr(String(data="hi"), "std_msgs/msg/String"))
    with pytest.raises(BagError, match="no default field for message type std_msgs/msg/String"):
        read_bag_signals(path)
    with pytest.raises(BagError, match="leads to str, not a number"):
        read_bag_signals(path, input_field="data", output_field="data")


@pytest.mark.parametrize("args, message", [
    (["identify", "--bag", "/no/bag"], "bag not found"),
    (["identify", "--bag", "/tmp", "--generations", "1"], "no metadata.yaml"),
])
def test_bag_errors_exit_nonzero_without_traceback(args, message):
    r = _spm(*args)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr


def _miso(n=800, seed=3):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (n, 2))
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 0.5 * y[t - 1] + 0.7 * u[t - 1, 0] - 0.4 * u[t - 1, 1] \
            + 0.3 * u[t - 2, 0] * u[t - 1, 1]
    return u, y + 1e-3 * rng.standard_normal(n)


def test_two_joint_efforts_from_one_jointstate_topic(tmp_path):
    u, y = _miso()
    bag = write_io_bag(tmp_path / "joints", u, y, input_topic="/joint_states",
                       input_names=["shoulder", "elbow"])
    # an independent reader: the mcap library sees JointState messages with two efforts
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(next(bag.glob("*.mcap")), "rb") as f:
        msgs = [(ch.topic, m) for _, ch, _, m in
                make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    joint = [m for t, m in msgs if t == "/joint_states"]
    assert len(joint) == 800 and list(joint[5].name) == ["shoulder", "elbow"]
    assert list(joint[5].effort) == u[5].tolist()

    sig = read_bag_signals(bag, input_topic="/joint_states", input_field="effort[0],effort[1]",
                           input_names="shoulder,elbow")
    assert np.array_equal(sig.u, u) and np.array_equal(sig.y, y) and sig.unpaired == 0
    assert sig.input_names == ("shoulder", "elbow")
    # the same topic, fields in the other order: the columns follow the given order
    swapped = read_bag_signals(bag, input_topic="/joint_states",
                               input_field="effort[1],effort[0]")
    assert np.array_equal(swapped.u, u[:, ::-1]) and swapped.input_names == ("u1", "u2")
    with pytest.raises(BagError, match="input_field lists 2 entries for 3 inputs"):
        read_bag_signals(bag, input_topic="/joint_states", input_field="effort[0],effort[1]",
                         input_names="a,b,c")
    r = _spm("identify", "--bag", str(bag), "--input-topic", "/joint_states",
             "--input-field", "effort[0],effort[1]", "--input-names", "shoulder,elbow",
             "--ny", "2", "--nu", "2", "--criterion", "bic", "--seed", "1", "--quiet",
             "--json", str(tmp_path / "m.json"))
    assert r.returncode == 0, r.stderr
    assert ("y(t) = 0.500y(t-1) + 0.700shoulder(t-1) - 0.400elbow(t-1) "
            "+ 0.300shoulder(t-2)*elbow(t-1)") in r.stdout


def test_inputs_on_two_topics_are_aligned_by_stamp(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    u, y = _miso(300)
    store = get_typestore(Stores.ROS2_JAZZY)
    T = store.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    Float, Vec = T["std_msgs/msg/Float64"], T["geometry_msgs/msg/Vector3Stamped"]
    Accel, A, V3 = T["geometry_msgs/msg/AccelStamped"], T["geometry_msgs/msg/Accel"], \
        T["geometry_msgs/msg/Vector3"]
    with Writer(tmp_path / "two", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c1 = w.add_connection("/torque", "geometry_msgs/msg/Vector3Stamped", typestore=store)
        c2 = w.add_connection("/cmd", "geometry_msgs/msg/Vector3Stamped", typestore=store)
        c3 = w.add_connection("/acc", "geometry_msgs/msg/AccelStamped", typestore=store)
        del Float
        for k in range(300):
            t = 10_000_000 * k
            h = Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id="")
            zero = V3(x=0.0, y=0.0, z=0.0)
            # the second input topic arrives late in the log (queued), which must not matter
            w.write(c1, t, store.serialize_cdr(Vec(header=h, vector=V3(
                x=float(u[k, 0]), y=0.0, z=0.0)), c1.msgtype))
            if k >= 5:
                t5 = 10_000_000 * (k - 5)
                h5 = Header(stamp=Time(sec=t5 // 10**9, nanosec=t5 % 10**9), frame_id="")
                w.write(c2, t, store.serialize_cdr(Vec(header=h5, vector=V3(
                    x=0.0, y=float(u[k - 5, 1]), z=0.0)), c2.msgtype))
            w.write(c3, t, store.serialize_cdr(Accel(header=h, accel=A(
                linear=V3(x=float(y[k]), y=0.0, z=0.0), angular=zero)), c3.msgtype))
    sig = read_bag_signals(tmp_path / "two", input_topic="/torque,/cmd",
                           input_field="vector.x,vector.y", output_topic="/acc")
    # the last 5 /cmd messages were never written: those samples cannot be aligned
    assert np.array_equal(sig.u, u[:295]) and np.array_equal(sig.y, y[:295])
    assert sig.topics == {"/torque": "geometry_msgs/msg/Vector3Stamped",
                          "/cmd": "geometry_msgs/msg/Vector3Stamped",
                          "/acc": "geometry_msgs/msg/AccelStamped"}
    assert sig.input_count == 595 and sig.unpaired == 10


def _skewed_bag(path, n: int = 300, skew_ns: int = 3_000_000):
    """Torque and acceleration at 100 Hz whose drivers stamp 3 ms apart (rosbags Writer)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from spm_sysid.core.io.bagio import typestore

    store = typestore()
    T = store.types
    header = lambda t: T["std_msgs/msg/Header"](  # noqa: E731
        stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9), frame_id="")
    vec = T["geometry_msgs/msg/Vector3"]
    rng = np.random.default_rng(0)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/robot_arm/torque", "geometry_msgs/msg/WrenchStamped",
                              typestore=store)
        co = w.add_connection("/robot_arm/acceleration", "geometry_msgs/msg/AccelStamped",
                              typestore=store)
        for k in range(n):
            t = 10_000_000 * k + 10**9
            wrench = T["geometry_msgs/msg/Wrench"](force=vec(x=0.0, y=0.0, z=0.0),
                                                   torque=vec(x=0.0, y=0.0, z=rng.random()))
            w.write(ci, t, store.serialize_cdr(T["geometry_msgs/msg/WrenchStamped"](
                header=header(t), wrench=wrench), "geometry_msgs/msg/WrenchStamped"))
            accel = T["geometry_msgs/msg/Accel"](linear=vec(x=rng.random(), y=0.0, z=0.0),
                                                 angular=vec(x=0.0, y=0.0, z=0.0))
            w.write(co, t + skew_ns, store.serialize_cdr(T["geometry_msgs/msg/AccelStamped"](
                header=header(t + skew_ns), accel=accel), "geometry_msgs/msg/AccelStamped"))
    return path


def test_stamps_out_of_step_say_the_tolerance_that_pairs_them(tmp_path):
    """Two drivers 3 ms apart: 'no ... matching stamps' said neither why nor what to do."""
    from spm_sysid.core.record import DataSpec, load_record

    bag = _skewed_bag(tmp_path / "skew")
    with pytest.raises(BagError, match=r"a median 3 ms from the nearest input's \(two drivers "
                                       r"or clocks out of step\?\): --stamp-tolerance 0\.0045"):
        read_bag_signals(bag)
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "identify", "--bag",
                        str(bag), "--stamp-tolerance", "0.0045", "--generations", "5",
                        "--quiet"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "data: bag " in r.stdout and "300 samples used" in r.stdout
    # the node reads a goal's bag with its stamp_tolerance (a float), as its topics
    record = load_record(DataSpec(bag=str(bag), bag_options={"stamp_tolerance": 0.0045}))
    assert len(record.y) == 300
    with pytest.raises(BagError, match="tolerance 0 ns"):  # 0 s is a tolerance, not a default
        load_record(DataSpec(bag=str(bag), bag_options={"stamp_tolerance": 0.0}))
    with pytest.raises(DataError, match="stamp_tolerance must be between 0 and 1, got 2.0"):
        load_record(DataSpec(bag=str(bag), bag_options={"stamp_tolerance": "2"}))


def test_a_sqlite3_bag_reads_and_its_db3_file_names_the_folder(tmp_path):
    """Humble's default storage: the folder reads; the .db3 file alone says to give it."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from spm_sysid.core.io.bagio import typestore

    store = typestore()
    Float64 = store.types["std_msgs/msg/Float64"]
    bag = tmp_path / "take"
    with Writer(bag, version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        cu = w.add_connection("/u", "std_msgs/msg/Float64", typestore=store)
        cy = w.add_connection("/y", "std_msgs/msg/Float64", typestore=store)
        for k in range(50):
            t = 10_000_000 * k + 10**9
            w.write(cu, t, store.serialize_cdr(Float64(data=float(k)), "std_msgs/msg/Float64"))
            w.write(cy, t, store.serialize_cdr(Float64(data=-float(k)),
                                               "std_msgs/msg/Float64"))
    sig = read_bag_signals(bag, input_topic="/u", output_topic="/y")
    assert sig.u.tolist() == list(range(50)) and sig.y.tolist() == [-k for k in range(50)]
    db3 = next(bag.glob("*.db3"))
    with pytest.raises(BagError, match=f"give its folder, {bag}, which holds metadata.yaml"):
        read_bag_signals(db3, input_topic="/u", output_topic="/y")
