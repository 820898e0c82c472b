"""The paper's seven exploration strategies, as small classes the actor and the learner share, each
next to its parameters (its section of the config, exploration.<section>): one module per rule.

Every strategy is a Max-Boltzmann rule with two numbers: with probability
``epsilon`` it explores, otherwise it takes the greedy action. Exploring samples
softmax(Q / kappa), or, when ``kappa`` is 0 ("no temperature", as the wire's
ExplorationState has it), a uniform action: the epsilon-greedy family is
(epsilon, 0), Softmax is (1, kappa) and Max-Boltzmann is (epsilon, kappa).
Until ``start()`` (updates start) every strategy is (1, 0): uniform random
actions.

The actor only calls ``act``. The learner calls the hooks after each update
(learner/feed.py) and sends ``state_dict()`` to the actors, which
``load_state_dict`` it:

- ``on_env_steps(total)``: the step-based schedule of decreasing epsilon-greedy
  (epsilon_greedy);
- ``on_update(q_before, q_after)``: VDBE (vdbe);
- ``on_returns(g_greedy, g_uniform)``: epsilon-BMC (bmc).

The modules: names (the one registry: what each strategy is called, its class, where its settings live),
base (the rule and the state every strategy shares, typed: its config sections,
its Counters and its own state_type), epsilon_greedy, vdbe, bmc, boltzmann
(Softmax and Max-Boltzmann), build (a strategy from a config or from another
process's params). The learner is the authority on the strategy: an actor builds
none of its own; it rebuilds the learner's from the typed exploration state
(common/wire/exploration_state.py ``follow``).
"""
