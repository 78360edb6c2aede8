"""episode_log: lock-step episodes rebuilt from timestamped streams, whatever the arrival order."""
import pytest

from gscan_ros.data.episode_log import (
    ABORTED,
    COMPLETE,
    EpisodeLog,
    IncompleteEpisode,
    StampedBuffer,
    UnpairedAction,
)
from gscan_ros.world.types import Action

WALK, TURN, EOS = Action.WALK, Action.TURN_LEFT, Action.EOS


def feed(log, events):
    """events: (kind, t_ns, value[, seq]) in arrival order; returns the records the actions closed."""
    records = []
    for kind, t, value, *seq in events:
        if kind == "actions":
            record = log.add_action(t, value, *seq)
            if record is not None:
                records.append(record)
        else:
            getattr(log, kind).add(t, value)
    return records


def lockstep_events(graph_t=50, actions=(WALK, TURN, EOS), t0=10, images=False, seq0=1):
    """World publishes situation+observation(+image) at t0; each action at t (publisher
    sequence number seq0, seq0 + 1, ...) and its reply at t+2."""
    events = [("situations", t0, "s0"), ("observations", t0 + 1, "o0")]
    if images:
        events.append(("images", t0 + 2, "i0"))
    events.append(("graphs", graph_t, "g"))
    t = graph_t + 10
    for k, action in enumerate(actions, start=1):
        events.append(("actions", t, action, seq0 + k - 1))
        if action is not EOS:
            events += [("situations", t + 1, f"s{k}"), ("observations", t + 2, f"o{k}")]
            if images:
                events.append(("images", t + 3, f"i{k}"))
        t += 10
    return events, t - 10


def test_in_order_streams_give_one_observation_per_action():
    [record] = feed(EpisodeLog(100), lockstep_events()[0])
    assert record.outcome == COMPLETE
    assert record.graph.value == "g"
    assert record.situation.value == "s0"
    assert [s.observation.value for s in record.steps] == ["o0", "o1", "o2"]
    assert [s.action.value for s in record.steps] == [WALK, TURN, EOS]
    assert record.actions == (WALK, TURN)
    assert record.start_ns == 11  # observation 0 predates the graph


def test_observation_delivered_before_the_action_that_caused_it():
    events, _ = lockstep_events()
    # Swap each action with the reply observation that follows it.
    swapped = list(events)
    for i, (kind, *_) in enumerate(events[:-1]):
        if kind == "actions" and events[i + 2][0] == "observations":
            swapped[i], swapped[i + 2] = events[i + 2], events[i]
    [record] = feed(EpisodeLog(100), swapped)
    assert [s.observation.value for s in record.steps] == ["o0", "o1", "o2"]


def test_a_preempted_episode_is_not_part_of_the_next():
    log = EpisodeLog(100)
    events, _ = lockstep_events(graph_t=50, actions=(WALK, WALK))  # never ends
    feed(log, events)
    later, _ = lockstep_events(graph_t=200, actions=(TURN, EOS), t0=150, seq0=3)
    [record] = feed(log, later[2:])  # the new graph and its steps (the world state is the old one's last)
    assert [s.action.value for s in record.steps] == [TURN, EOS]
    assert record.steps[0].observation.value == "o2"  # the reply to the preempted episode's last walk
    assert record.situation.value == "s2"


def test_images_pair_with_their_observation():
    [record] = feed(EpisodeLog(100, images=True), lockstep_events(images=True)[0])
    assert [s.image.value for s in record.steps] == ["i0", "i1", "i2"]


@pytest.mark.parametrize("missing", ["graphs", "observations", "situations"])
def test_missing_messages_raise_incomplete_episode(missing):
    events, _ = lockstep_events()
    with pytest.raises(IncompleteEpisode):
        feed(EpisodeLog(100), [e for e in events if e[0] != missing])


# -- pairing: a stray <eos> from another publisher (issue: it closed a 3-action episode as
#    complete, and the real episode was then dropped) ------------------------------------
REAL = (WALK, WALK, TURN, WALK, EOS)


def with_stray(events, after_kind_value, stray):
    """`events` with the `stray` action inserted 1 ns after the event whose value is `after_kind_value`."""
    i = next(i for i, e in enumerate(events) if e[2] == after_kind_value)
    return events[: i + 1] + [("actions", events[i][1] + 1, *stray)] + events[i + 1 :]


def test_a_stray_eos_from_another_publisher_closes_nothing():
    events, _ = lockstep_events(actions=REAL)
    log = EpisodeLog(100)
    stray_at = next(i for i, e in enumerate(events) if e[2] == "o3") + 1  # answers o3 before the real action
    feed(log, events[:stray_at])
    with pytest.raises(UnpairedAction, match="not the next message of the episode's action publisher"):
        log.add_action(events[stray_at - 1][1] + 1, EOS, 1)  # a fresh publisher's first message
    [record] = feed(log, events[stray_at:])
    assert record.outcome == COMPLETE and record.actions == REAL[:-1]


def test_a_stray_eos_sent_before_the_worlds_reply_closes_nothing_even_without_sequence_numbers():
    events, _ = lockstep_events(actions=REAL)
    events = [e[:3] for e in events]  # a middleware that reports no sequence numbers
    log = EpisodeLog(100)
    feed(log, events[:-1])  # up to o4, the world's reply to the 4th action
    fourth_action_t = events[-4][1]
    with pytest.raises(UnpairedAction, match="before the world replied"):
        log.add_action(fourth_action_t + 1, EOS)  # sent before o4: it cannot answer it
    [record] = feed(log, events[-1:])
    assert record.actions == REAL[:-1]


def test_a_stray_action_inside_the_episode_is_left_out_and_counted():
    events, _ = lockstep_events(actions=REAL)
    [record] = feed(EpisodeLog(100), with_stray(events, "o2", (TURN, 7)))
    assert record.actions == REAL[:-1] and record.left_out == 1


def test_a_second_eos_after_the_episode_ended_is_unpaired():
    events, eos_t = lockstep_events()
    log = EpisodeLog(100)
    feed(log, events)
    with pytest.raises(UnpairedAction, match="since the last one ended"):
        log.add_action(eos_t + 5, EOS, 1)


# -- resets: the running episode ends, recorded as aborted -------------------------------
def test_a_reset_mid_episode_records_the_chain_so_far_as_aborted():
    events, _ = lockstep_events(actions=REAL)
    cut = next(i for i, e in enumerate(events) if e[2] == "o2") + 1  # two actions answered
    log = EpisodeLog(100)
    assert feed(log, events[:cut]) == []
    reset_t = events[cut - 1][1] + 3
    record = log.add_reset(reset_t)
    assert record.outcome == ABORTED and record.reason == "the world was reset"
    assert record.actions == (WALK, WALK)
    assert [s.observation.value for s in record.steps] == ["o0", "o1", "o2"]  # o2: where the last walk led
    assert record.steps[-1].action is None
    # The policy's late actions and any <eos> for the old command belong to no episode.
    with pytest.raises(UnpairedAction, match="since the last one ended"):
        log.add_action(reset_t + 50, EOS, 4)


def test_the_episode_after_a_reset_starts_in_the_new_world():
    log = EpisodeLog(100)
    events, _ = lockstep_events(actions=(WALK, WALK))
    feed(log, events)
    assert log.add_reset(200).outcome == ABORTED
    later, _ = lockstep_events(graph_t=250, actions=(TURN, EOS), t0=201, seq0=3)
    [record] = feed(log, later)
    assert record.situation.value == "s0" and record.situation.t_ns == 201  # the new world's
    assert record.actions == (TURN,)


def test_a_reset_with_no_running_episode_records_nothing():
    log = EpisodeLog(100)
    feed(log, lockstep_events()[0])  # complete
    assert log.add_reset(500) is None
    log.graphs.add(600, "g2")  # a command the policy never acted on
    assert log.add_reset(700) is None


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


def test_an_eos_that_arrives_before_the_last_replies_closes_once_they_arrive():
    events, _ = lockstep_events(actions=(WALK, TURN, EOS))
    log = EpisodeLog(100)
    late = [e for e in events if e[0] == "observations" and e[2] == "o2"]  # the reply to the last action
    eos_event = next(e for e in events if e[0] == "actions" and e[2] is EOS)
    feed(log, [e for e in events if e not in late and e is not eos_event])
    with pytest.raises(IncompleteEpisode):
        log.add_action(*eos_event[1:])
    for kind, t, value in late:
        getattr(log, kind).add(t, value)
    record = log.close(log.actions.latest_before(eos_event[1], inclusive=True))
    assert record.outcome == COMPLETE and [s.observation.value for s in record.steps] == ["o0", "o1", "o2"]


def test_the_next_episode_starts_from_the_state_the_last_one_ended_in():
    """A command right after an <eos>: no new state is published, the last one starts it."""
    log = EpisodeLog(100)
    events, end = lockstep_events(actions=(WALK, EOS))
    [first] = feed(log, events)
    second_graph = end + 20
    [second] = feed(log, [("graphs", second_graph, "g2"), ("actions", second_graph + 10, TURN, 3),
                          ("situations", second_graph + 11, "s2"), ("observations", second_graph + 12, "o2"),
                          ("actions", second_graph + 20, EOS, 4)])
    assert [s.observation.value for s in second.steps] == ["o1", "o2"]
    assert second.situation.value == "s1"  # published with o1, before the first episode ended
    assert second.actions == (TURN,) and first.actions == (WALK,)
