from learner.pacing import StepClock


def test_no_updates_are_due_before_updates_start():
    clock = StepClock()
    clock.observe(5_000)
    assert clock.updates_due(4) == 0
    assert not clock.may_update(0, 4, 0.1)


def test_one_update_per_four_steps_after_the_start():
    clock = StepClock()
    clock.observe(1_000)
    clock.start_updates()
    clock.observe(1_400)
    assert clock.updates_due(4) == 100  # (1,400 - 1,000) / 4
    assert clock.may_update(99, 4, 0.0)
    assert clock.may_update(100, 4, 0.0)  # one update of slack
    assert not clock.may_update(101, 4, 0.0)
    assert clock.may_update(109, 4, 0.1)  # 10% of 100 due
    assert not clock.may_update(110, 4, 0.1)


def test_a_restarted_replay_counts_from_zero_again():
    clock = StepClock()
    clock.observe(800)
    clock.observe(1_000)
    clock.observe(30)  # the replay restarted and has seen 30 new steps
    clock.observe(50)
    assert clock.env_steps == 1_050


def test_state_survives_a_learner_restart():
    clock = StepClock()
    clock.observe(2_000)
    clock.start_updates()
    clock.observe(2_400)
    resumed = StepClock()
    resumed.load_state_dict(clock.state_dict())
    resumed.observe(2_480)  # the same replay went on while the learner was down
    assert resumed.env_steps == 2_480
    assert resumed.updates_due(4) == 120
    restarted = StepClock()
    restarted.load_state_dict(clock.state_dict())
    restarted.observe(100)  # a new replay counts from zero
    assert restarted.env_steps == 2_500
