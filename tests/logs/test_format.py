"""The run-log format: exact round trips; the MCAP package's generic reader and the jsonschema
package as independent oracles of what we write; files written by hand with the bare MCAP
writer as independent inputs of what we read; clear errors on corrupt or foreign files."""

from __future__ import annotations

import dataclasses
import json
import math
import random
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from torchcontact.logs import ContactTruth, RunLog, read_run, write_run

F64 = torch.float64
# The format's channels as docs/logs.md documents them: topic -> schema name.
DOCUMENTED = {
    "/run/info": "torchcontact.logs.v1.RunInfo",
    "/robot/state": "torchcontact.logs.v1.RobotState",
    "/robot/command": "torchcontact.logs.v1.RobotCommand",
    "/camera/pose": "torchcontact.logs.v1.CameraPose",
    "/tactile/readings": "torchcontact.logs.v1.TactileReadings",
    "/estimate/prior": "torchcontact.logs.v1.Prior",
    "/ground_truth/state": "torchcontact.logs.v1.BodyStates",
    "/ground_truth/contacts": "torchcontact.logs.v1.Contacts",
    "/ground_truth/parameters": "torchcontact.logs.v1.Parameters",
}
# float64 values whose decimal forms are the hard cases: signed zero, the least subnormal, the
# least normal, the largest finite, and fractions without a finite binary expansion.
EXTREMES = [0.0, -0.0, 5e-324, -2.2250738585072014e-308, 1.7976931348623157e308, 0.1, 1 / 3]
STEP_NS = 10_000_000


def make_run(T: int = 6, J: int = 4, S: int = 3, K: int = 5, seed: int = 0) -> RunLog:
    """A run with every optional part, random values and the extremes, vision missing at
    instants 0 and 3."""
    gen = torch.Generator().manual_seed(seed)

    def randn(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=gen, dtype=F64)

    position = randn(T + 1, J)
    position.view(-1)[: len(EXTREMES)] = torch.tensor(EXTREMES, dtype=F64)
    vision = randn(T + 1, 3)
    vision[0] = math.nan
    if T >= 3:
        vision[3] = math.nan
    A = randn(6, 6)
    contacts = ContactTruth(
        mode=torch.randint(0, 4, (T, K), generator=gen),
        normal_impulse=randn(T, K).abs(),
        friction_impulse=randn(T, K, 2).abs(),
        point=randn(T, K, 2),
        normal=torch.nn.functional.normalize(randn(T, K, 2), dim=-1),
        candidate=torch.rand(T, K, generator=gen) > 0.5,
        solver=torch.randint(0, 3, (T,), generator=gen),
    )
    return RunLog(
        name="run",
        h=0.01,
        body="box",
        joints=tuple(f"j{i}" for i in range(J)),
        time_ns=1_700_000_000_000_000_000 + STEP_NS * torch.arange(T + 1),
        robot_position=position,
        robot_velocity=randn(T, J),
        vision=vision,
        tactile=torch.rand(T, S, generator=gen) > 0.5,
        source={"experiment": "test", "nested": {"a": [1, 2.5, "x"], "b": None}},
        prior_mean=randn(6),
        prior_covariance=A @ A.T,
        bodies=("box", "lid"),
        truth_pose=randn(T + 1, 2, 3),
        truth_twist=randn(T + 1, 2, 3),
        truth_contacts=contacts,
        parameters={"friction": 0.37, "mass": 1e-3},
    )


TENSORS = ("time_ns", "robot_position", "robot_velocity", "tactile", "prior_mean")
TENSORS += ("prior_covariance", "truth_pose", "truth_twist")
CONTACT_TENSORS = tuple(f.name for f in dataclasses.fields(ContactTruth))


def assert_same(a: torch.Tensor, b: torch.Tensor, name: str) -> None:
    assert (a.dtype, a.shape) == (b.dtype, b.shape), name
    assert bool((a == b).all()), name  # the format is lossless: exact equality is the claim
    if a.is_floating_point():
        assert bool((a.signbit() == b.signbit()).all()), name  # -0.0 stays -0.0


def assert_same_run(run: RunLog, back: RunLog) -> None:
    for name in TENSORS:
        assert_same(getattr(run, name), getattr(back, name), name)
    assert run.truth_contacts is not None
    assert back.truth_contacts is not None
    for name in CONTACT_TENSORS:
        assert_same(getattr(run.truth_contacts, name), getattr(back.truth_contacts, name), name)
    seen = ~run.vision[:, 0].isnan()
    assert bool((seen == ~back.vision.isnan().any(-1)).all())
    assert bool(back.vision[~seen].isnan().all())
    assert_same(run.vision[seen], back.vision[seen], "vision")
    for name in ("name", "h", "body", "joints", "bodies", "source", "parameters"):
        assert getattr(run, name) == getattr(back, name), name


def test_round_trip_is_exact(tmp_path: Path) -> None:
    run = make_run()
    assert_same_run(run, read_run(write_run(tmp_path / "run.mcap", run)))


@settings(max_examples=40, deadline=None, database=None, derandomize=True)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=8, max_size=8))
def test_any_finite_float64_round_trips(
    tmp_path_factory: pytest.TempPathFactory, values: list[float]
) -> None:
    run = make_run(T=1, J=4)
    run = dataclasses.replace(run, robot_position=torch.tensor(values, dtype=F64).reshape(2, 4))
    path = tmp_path_factory.mktemp("floats") / "run.mcap"
    assert_same(run.robot_position, read_run(write_run(path, run)).robot_position, "position")


def test_a_run_without_the_optional_parts_round_trips(tmp_path: Path) -> None:
    full = make_run()
    run = RunLog(
        name="bare",
        h=0.02,
        body="box",
        joints=full.joints,
        time_ns=full.time_ns,
        robot_position=full.robot_position,
        robot_velocity=full.robot_velocity,
        vision=full.vision,
        tactile=full.tactile[:, :0],  # no tactile sensors
    )
    back = read_run(write_run(tmp_path / "bare.mcap", run))
    assert back.prior_mean is None
    assert back.truth_pose is None
    assert back.truth_contacts is None
    assert back.parameters == {}
    assert back.bodies == ()
    assert back.source == {}
    assert back.tactile.shape == (run.steps, 0)
    assert_same(run.robot_position, back.robot_position, "robot_position")


def test_the_generic_mcap_reader_reads_our_files(tmp_path: Path) -> None:
    run = make_run()
    T = run.steps
    path = write_run(tmp_path / "run.mcap", run)
    with path.open("rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic: c for c in summary.channels.values()}
        assert {t: summary.schemas[c.schema_id].name for t, c in topics.items()} == DOCUMENTED
        validators = {}
        for topic, channel in topics.items():
            schema = summary.schemas[channel.schema_id]
            assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json")
            document = json.loads(schema.data)
            jsonschema.Draft202012Validator.check_schema(document)
            validators[topic] = jsonschema.Draft202012Validator(document)
        messages: dict[str, list[tuple[int, Any]]] = {topic: [] for topic in topics}
        for _, channel, message in reader.iter_messages():
            decoded = json.loads(message.data)
            validators[channel.topic].validate(decoded)
            assert message.publish_time == message.log_time
            messages[channel.topic].append((message.log_time, decoded))
    counts = {topic: len(found) for topic, found in messages.items()}
    once = ("/run/info", "/estimate/prior", "/ground_truth/parameters")
    assert counts == {
        **dict.fromkeys(once, 1),
        "/robot/state": T + 1,
        "/ground_truth/state": T + 1,
        "/robot/command": T,
        "/tactile/readings": T,
        "/ground_truth/contacts": T,
        "/camera/pose": T + 1 - 2,  # none at the two instants without vision
    }
    times = [time for time, _ in messages["/robot/state"]]
    assert times == run.time_ns.tolist()
    # the numbers as any JSON reader sees them, exactly
    positions = torch.tensor([m["position"] for _, m in messages["/robot/state"]], dtype=F64)
    assert_same(run.robot_position, positions, "position")
    velocities = [m["velocity"] for _, m in messages["/robot/command"]]
    assert velocities == run.robot_velocity.tolist()
    assert [time for time, _ in messages["/camera/pose"]] == [times[k] for k in (1, 2, 4, 5, 6)]
    info = messages["/run/info"][0][1]
    assert info["h"] == 0.01
    assert info["joints"] == list(run.joints)


# ----------------------------------------------------------------------------------------------
# files written by hand with the bare MCAP writer


def write_by_hand(
    path: Path,
    messages: list[tuple[str, int, str]],
    *,
    version: int = 1,
    schema_encoding: str = "jsonschema",
    message_encoding: str = "json",
) -> Path:
    """An MCAP file of ``(topic, log time, JSON text)`` messages, each topic with a schema
    named as the docs say (``{}`` as the schema: the reader does not read it)."""
    with path.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.NONE)
        writer.start()
        ids = {}
        for topic, time, text in messages:
            if topic not in ids:
                name = DOCUMENTED[topic].replace(".v1.", f".v{version}.")
                schema = writer.register_schema(name, schema_encoding, b"{}")
                ids[topic] = writer.register_channel(topic, message_encoding, schema)
            writer.add_message(ids[topic], log_time=time, data=text.encode(), publish_time=time)
        writer.finish()  # type: ignore[no-untyped-call]
    return path


INFO = (
    '{{"name": "{name}", "h": 0.5, "body": "box", "joints": ["a", "b"], "bodies": [], '
    '"source": {{}}}}'
)


def hand_messages() -> list[tuple[str, int, str]]:
    """Two steps, two robot coordinates, one tactile sensor, vision at instant 2 only; the
    numbers as JSON integers where they are whole (any JSON writer's choice)."""
    info = INFO.format(name="hand")
    return [
        ("/run/info", 100, info),
        ("/robot/state", 100, '{"position": [0, 1]}'),
        ("/robot/command", 100, '{"velocity": [2, -3]}'),
        ("/tactile/readings", 100, '{"triggered": [true]}'),
        ("/robot/state", 600, '{"position": [1, -0.5]}'),
        ("/robot/command", 600, '{"velocity": [0.25, 1e-3]}'),
        ("/tactile/readings", 600, '{"triggered": [false]}'),
        ("/robot/state", 1100, '{"position": [1.125, -2]}'),
        ("/camera/pose", 1100, '{"frame_id": "world", "pose": [1, 2, 3.5]}'),
    ]


def test_a_file_written_by_hand_reads_as_documented(tmp_path: Path) -> None:
    run = read_run(write_by_hand(tmp_path / "hand.mcap", hand_messages()))
    assert (run.name, run.h, run.body, run.joints, run.steps) == ("hand", 0.5, "box", ("a", "b"), 2)
    assert run.time_ns.tolist() == [100, 600, 1100]
    assert run.robot_position.tolist() == [[0.0, 1.0], [1.0, -0.5], [1.125, -2.0]]
    assert run.robot_velocity.tolist() == [[2.0, -3.0], [0.25, 1e-3]]
    assert run.tactile.tolist() == [[True], [False]]
    assert bool(run.vision[:2].isnan().all())
    assert run.vision[2].tolist() == [1.0, 2.0, 3.5]
    assert run.robot_position.dtype == F64
    assert run.time_ns.dtype == torch.int64


def _replace(index: int, text: str) -> Callable[[list[tuple[str, int, str]]], None]:
    def edit(messages: list[tuple[str, int, str]]) -> None:
        topic, time, _ = messages[index]
        messages[index] = (topic, time, text)

    return edit


def _drop(topic: str) -> Callable[[list[tuple[str, int, str]]], None]:
    def edit(messages: list[tuple[str, int, str]]) -> None:
        messages[:] = [m for m in messages if m[0] != topic]

    return edit


def _append(message: tuple[str, int, str]) -> Callable[[list[tuple[str, int, str]]], None]:
    return lambda messages: messages.append(message)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (_drop("/tactile/readings"), r"lacks the required channels \['/tactile/readings'\]"),
        (_drop("/run/info"), r"lacks the required channels \['/run/info'\]"),
        (
            _replace(1, '{"position": [0]}'),
            r"/robot/state at 100 ns: field 'position': expected a list of 2",
        ),
        (_replace(1, '{"position": [0, NaN]}'), "expected a finite number"),
        (_replace(1, '{"position": [0, true]}'), "expected a number, got True"),
        (_replace(1, '{"pos": [0, 1]}'), r"lacks the fields \['position'\]"),
        (_replace(1, "[0, 1]"), "expected a JSON object"),
        (_replace(1, "{position"), "the message is not JSON"),
        (_replace(3, '{"triggered": [1]}'), "expected a boolean, got 1"),
        (_replace(8, '{"frame_id": "world", "pose": [1, 2]}'), "expected a list of 3"),
        (
            _append(("/camera/pose", 700, '{"frame_id": "world", "pose": [1, 2, 3]}')),
            "not at an instant",
        ),
        (_append(("/robot/command", 1100, '{"velocity": [0, 0]}')), "not at an instant"),
        (_append(("/tactile/readings", 600, '{"triggered": [true]}')), "a second message"),
        (_drop("/robot/command"), r"lacks the required channels \['/robot/command'\]"),
        (
            _replace(
                0,
                INFO.format(name=""),
            ),
            "name: expected a non-empty str",
        ),
    ],
)
def test_a_message_that_does_not_fit_is_a_value_error(
    tmp_path: Path, edit: Callable[[list[tuple[str, int, str]]], None], match: str
) -> None:
    messages = hand_messages()
    edit(messages)
    with pytest.raises(ValueError, match=match):
        read_run(write_by_hand(tmp_path / "bad.mcap", messages))


def test_an_unknown_schema_version_is_a_value_error(tmp_path: Path) -> None:
    path = write_by_hand(tmp_path / "v2.mcap", hand_messages(), version=2)
    with pytest.raises(ValueError, match=r"format version 2; this reader knows version 1"):
        read_run(path)


@pytest.mark.parametrize(
    ("keywords", "match"),
    [
        ({"schema_encoding": "protobuf"}, "schema encoding 'protobuf'"),
        ({"message_encoding": "cbor"}, "message encoding 'cbor'"),
    ],
)
def test_a_foreign_encoding_is_a_value_error(
    tmp_path: Path, keywords: dict[str, str], match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        read_run(write_by_hand(tmp_path / "foreign.mcap", hand_messages(), **keywords))


def test_other_tools_channels_ride_along(tmp_path: Path) -> None:
    path = tmp_path / "extra.mcap"
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start()
        schema = writer.register_schema("foxglove.Log", "jsonschema", b"{}")
        channel = writer.register_channel("/rosout", "json", schema)
        writer.add_message(channel, log_time=100, data=b'{"message": "hi"}', publish_time=100)
        ids = {}
        for topic, time, text in hand_messages():
            if topic not in ids:
                s = writer.register_schema(DOCUMENTED[topic], "jsonschema", b"{}")
                ids[topic] = writer.register_channel(topic, "json", s)
            writer.add_message(ids[topic], log_time=time, data=text.encode(), publish_time=time)
        writer.finish()  # type: ignore[no-untyped-call]
    assert read_run(path).steps == 2


# ----------------------------------------------------------------------------------------------
# corrupt files


def test_a_file_that_is_not_mcap_is_a_value_error(tmp_path: Path) -> None:
    path = tmp_path / "notes.mcap"
    path.write_text("not a log\n")
    with pytest.raises(ValueError, match="is not a readable MCAP file"):
        read_run(path)
    with pytest.raises(ValueError, match="is not a readable MCAP file"):
        read_run(tmp_path / "missing.mcap")
    with pytest.raises(ValueError, match=r"path: expected a str or os\.PathLike"):
        read_run(3)  # type: ignore[arg-type]


def test_every_truncation_is_a_value_error(tmp_path: Path) -> None:
    data = write_run(tmp_path / "run.mcap", make_run()).read_bytes()
    cut = tmp_path / "cut.mcap"
    for end in range(0, len(data), 61):
        cut.write_bytes(data[:end])
        with pytest.raises(ValueError, match=r"cut\.mcap"):
            read_run(cut)


def test_a_flipped_bit_is_a_value_error_or_changes_nothing(tmp_path: Path) -> None:
    # The chunks' CRCs cover every message; a flip elsewhere (an index, a schema's text) may
    # leave the content readable, and then it must read back unchanged.
    run = make_run()
    data = write_run(tmp_path / "run.mcap", run).read_bytes()
    flipped = tmp_path / "flipped.mcap"
    rng = random.Random(0)
    outcomes = {"error": 0, "same": 0}
    for _ in range(150):
        corrupt = bytearray(data)
        corrupt[rng.randrange(len(corrupt))] ^= 1 << rng.randrange(8)
        flipped.write_bytes(bytes(corrupt))
        try:
            back = read_run(flipped)
        except ValueError:
            outcomes["error"] += 1
            continue
        assert_same_run(run, back)
        outcomes["same"] += 1
    assert outcomes["error"] > 50  # most bytes are message data under a CRC


# ----------------------------------------------------------------------------------------------
# bad runs


def _bad(**changes: Any) -> Callable[[RunLog], RunLog]:
    return lambda run: dataclasses.replace(run, **changes)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (
            lambda r: dataclasses.replace(r, robot_position=r.robot_position.float()),
            "robot_position: expected a torch.float64",
        ),
        (
            lambda r: dataclasses.replace(r, robot_velocity=r.robot_velocity[1:]),
            "robot_velocity: expected",
        ),
        (
            lambda r: dataclasses.replace(r, robot_velocity=r.robot_velocity * math.inf),
            "robot_velocity: expected finite",
        ),
        (
            lambda r: dataclasses.replace(
                r, vision=torch.where(torch.arange(3) == 0, math.nan, r.vision)
            ),
            "vision: expected finite rows or all-NaN rows",
        ),
        (
            lambda r: dataclasses.replace(r, time_ns=r.time_ns.flip(0)),
            "time_ns: expected non-negative, strictly increasing",
        ),
        (
            lambda r: dataclasses.replace(r, tactile=r.tactile.long()),
            "tactile: expected a torch.bool",
        ),
        (_bad(prior_covariance=None), "prior_mean, prior_covariance: give both or neither"),
        (_bad(bodies=()), "bodies: name the bodies of truth_pose"),
        (_bad(h=0.0), "h: expected a finite float > 0"),
        (_bad(joints=("a", "a", "b", "c")), "joints: expected distinct names"),
        (
            _bad(parameters={"friction": math.nan}),
            "parameters: expected a dict of str to finite float",
        ),
    ],
)
def test_a_bad_run_names_the_field(change: Callable[[RunLog], RunLog], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        change(make_run())


def test_a_source_that_json_cannot_hold_is_a_value_error(tmp_path: Path) -> None:
    for source in ({"x": object()}, {"x": math.nan}):
        run = dataclasses.replace(make_run(), source=source)
        with pytest.raises(ValueError, match="/run/info: the message is not JSON-able"):
            write_run(tmp_path / "run.mcap", run)
    assert not (tmp_path / "run.mcap").exists()


def test_importing_the_logs_loads_no_heavy_package() -> None:
    code = "import sys, torchcontact.logs; print(' '.join(sorted(sys.modules)))"
    loaded = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    ).stdout.split()
    heavy = ("gymnasium", "pytorch_kinematics", "matplotlib", "scipy", "torchcontact.filters")
    assert [name for name in heavy if name in loaded] == []
