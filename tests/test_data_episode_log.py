"""episode_log: lock-step episodes rebuilt from timestamped streams, whatever the arrival order."""
import pytest

from gscan_ros.data.episode_log import IncompleteEpisode, StampedBuffer, assemble_episode
from gscan_ros.world.types import Action

WALK, TURN, EOS = Action.WALK, Action.TURN_LEFT, Action.EOS


def buffers(images=False):
    names = ("graphs", "actions", "observations", "situations") + (("images",) if images else ())
    return {name: StampedBuffer(100) for name in names}


def feed(b, events):
    """events: (kind, t_ns, value) in arrival order."""
    for kind, t, value in events:
        b[kind].add(t, value)


def lockstep_events(graph_t=50, actions=(WALK, TURN, EOS), t0=10, images=False):
    """World publishes situation+observation(+image) at t0; each action at t and its reply at t+2."""
    events = [("situations", t0, "s0"), ("observations", t0 + 1, "o0")]
    if images:
        events.append(("images", t0 + 2, "i0"))
    events.append(("graphs", graph_t, "g"))
    t = graph_t + 10
    for k, action in enumerate(actions, start=1):
        events.append(("actions", t, action))
        if action is not EOS:
            events += [("situations", t + 1, f"s{k}"), ("observations", t + 2, f"o{k}")]
            if images:
                events.append(("images", t + 3, f"i{k}"))
        t += 10
    return events, t - 10


def test_in_order_streams_give_one_observation_per_action():
    b = buffers()
    events, eos_t = lockstep_events()
    feed(b, events)
    record = assemble_episode(eos_t, b["graphs"], b["actions"], b["observations"], b["situations"])
    assert record.graph.value == "g"
    assert record.situation.value == "s0"
    assert [s.observation.value for s in record.steps] == ["o0", "o1", "o2"]
    assert [s.action.value for s in record.steps] == [WALK, TURN, EOS]
    assert record.actions == (WALK, TURN)
    assert record.start_ns == 11  # observation 0 predates the graph


def test_observation_delivered_before_the_action_that_caused_it():
    b = buffers()
    events, eos_t = lockstep_events()
    # Swap each action with the reply observation that follows it.
    swapped = list(events)
    for i, (kind, _, _) in enumerate(events[:-1]):
        if kind == "actions" and events[i + 2][0] == "observations":
            swapped[i], swapped[i + 2] = events[i + 2], events[i]
    feed(b, swapped)
    record = assemble_episode(eos_t, b["graphs"], b["actions"], b["observations"], b["situations"])
    assert [s.observation.value for s in record.steps] == ["o0", "o1", "o2"]


def test_a_preempted_episode_is_not_part_of_the_next():
    b = buffers()
    events, _ = lockstep_events(graph_t=50, actions=(WALK, WALK))  # never ends
    feed(b, events)
    later, eos_t = lockstep_events(graph_t=200, actions=(TURN, EOS), t0=150)
    feed(b, later[2:])  # the new graph and its steps (the world state is the old one's last)
    record = assemble_episode(eos_t, b["graphs"], b["actions"], b["observations"], b["situations"])
    assert [s.action.value for s in record.steps] == [TURN, EOS]
    assert record.steps[0].observation.value == "o2"  # the reply to the preempted episode's last walk
    assert record.situation.value == "s2"


def test_images_pair_with_their_observation():
    b = buffers(images=True)
    events, eos_t = lockstep_events(images=True)
    feed(b, events)
    record = assemble_episode(eos_t, b["graphs"], b["actions"], b["observations"], b["situations"], b["images"])
    assert [s.image.value for s in record.steps] == ["i0", "i1", "i2"]


@pytest.mark.parametrize("missing", ["graphs", "observations", "situations"])
def test_missing_messages_raise_incomplete_episode(missing):
    b = buffers()
    events, eos_t = lockstep_events()
    feed(b, [e for e in events if e[0] != missing])
    with pytest.raises(IncompleteEpisode):
        assemble_episode(eos_t, b["graphs"], b["actions"], b["observations"], b["situations"])


def test_buffer_is_bounded_and_sorted():
    buf = StampedBuffer(3)
    for t in (1, 5, 3, 4, 2):
        buf.add(t, t)
    assert len(buf) == 3
    assert [i.t_ns for i in buf.between(0, 100)] == [3, 4, 5]  # the newest three, in time order
    assert buf.latest_before(4).t_ns == 3
    assert buf.latest_before(4, inclusive=True).t_ns == 4
    assert buf.first_after(4).t_ns == 5
    buf.drop_until(4)
    assert [i.t_ns for i in buf.between(0, 100)] == [4, 5]
