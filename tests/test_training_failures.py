"""Failure kinds: a failed episode classified by replaying both action sequences."""
from gscan_ros.data.episode import Episode
from gscan_ros.model.policy import Policy
from gscan_ros.training.evaluate import EvalResult, Prediction, evaluate_episodes, failure_kind
from gscan_ros.training.failures import FAILURE_KINDS
from gscan_ros.world import Action, Heading, Position, Situation, WorldObject, demonstrate

from model_support import tiny_checkpoint, walk_episodes

L, R, W = Action.TURN_LEFT, Action.TURN_RIGHT, Action.WALK
CIRCLE = WorldObject("circle", "red", 1, Position(1, 1))
SQUARE = WorldObject("square", "blue", 2, Position(3, 5))
SITUATION = Situation(Position(3, 3), Heading.EAST, (CIRCLE, SQUARE), CIRCLE)


def predicted(command: str, actions: list[Action]) -> Prediction:
    episode = Episode(command, SITUATION, tuple(demonstrate(SITUATION, command)), split="test")
    return Prediction(episode, list(actions))


def test_each_kind_of_failure():
    gold = demonstrate(SITUATION, "walk to a circle")
    assert gold == [L, L, W, W, R, W, W]  # west along the row, then north
    assert failure_kind(predicted("walk to a circle", gold)) is None
    assert failure_kind(predicted("walk to a circle", [L, W, W, L, W, W])) == "right_end_state"  # north first
    assert failure_kind(predicted("walk to a circle", gold + [W])) == "wrong_end_state"  # walked on past it
    assert failure_kind(predicted("walk to a circle", [W, W])) == "target_not_reached"  # to the square
    assert failure_kind(predicted("walk to a circle", gold + [Action.STAY] * 120)) == "no_stop"
    assert failure_kind(predicted("walk to a circle", gold + [Action.STAY] * 120), max_steps=200) == "right_end_state"


def test_an_object_left_elsewhere_is_a_wrong_end_state():
    gold = demonstrate(SITUATION, "push a circle")
    assert gold[-1] is Action.PUSH
    assert failure_kind(predicted("push a circle", gold[:-1])) == "wrong_end_state"  # one push short
    assert failure_kind(predicted("push a circle", gold[:-1] + [Action.STAY, Action.PUSH])) == "right_end_state"


def test_summary_counts_failures_per_split():
    preds = [predicted("walk to a circle", a) for a in ([L, L, W, W, R, W, W], [W, W], [W, W, W], [L, W, W, L, W, W])]
    failures = EvalResult(preds).summary()["test"]["failures"]
    assert list(failures) == list(FAILURE_KINDS)
    assert failures == {"no_stop": 0, "target_not_reached": 2, "wrong_end_state": 0, "right_end_state": 1}


def test_summary_groups_episodes_by_whether_the_gold_moves_the_target():
    """A push against the wall moves nothing: its gold has no PUSH and counts as 'no'."""
    walled = WorldObject("circle", "red", 1, Position(3, 5))
    against_wall = Situation(Position(3, 3), Heading.EAST, (walled, WorldObject("square", "blue", 2, Position(0, 0))),
                             walled)
    stuck = Episode("push a circle", against_wall, tuple(demonstrate(against_wall, "push a circle")), split="test")
    assert Action.PUSH not in stuck.actions
    moved = predicted("push a circle", demonstrate(SITUATION, "push a circle"))
    assert Action.PUSH in moved.episode.actions
    preds = [moved, predicted("push a circle", [W]), Prediction(stuck, list(stuck.actions))]
    groups = EvalResult(preds).summary()["test"]["by_group"]
    assert groups["moves_target"] == {"no": {"examples": 1, "exact_match": 100.0},
                                      "yes": {"examples": 2, "exact_match": 50.0}}
    assert groups["verb"] == {"push": {"examples": 3, "exact_match": 66.67}}


def test_a_prediction_longer_than_its_own_cap_never_stopped():
    """The cap an evaluation decoded with decides whether the last action was an EOS."""
    gold = demonstrate(SITUATION, "walk to a circle")
    long = predicted("walk to a circle", gold + [Action.STAY] * 10)  # 17 actions
    assert long.failure == "right_end_state"  # under the default cap of 120: it stopped
    capped = Prediction(long.episode, long.actions, max_steps=12)
    assert capped.failure == "no_stop"


def test_evaluation_classifies_failures_at_the_cap_it_decoded_with(tmp_path):
    policy = Policy.from_checkpoint(tiny_checkpoint(tmp_path / "tiny.pt", seed=1))  # a seed that never stops
    result = evaluate_episodes(policy, walk_episodes(8), max_steps=2)
    assert {p.max_steps for p in result.predictions} == {2}
    assert any(len(p.actions) > 2 for p in result.predictions)  # some ran into the cap
    for p in result.predictions:
        assert (p.failure == "no_stop") == (len(p.actions) > 2)
