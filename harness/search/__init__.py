"""Corner-case search campaigns (``hil search``).

A campaign drives the AI through many *episodes*: lockstep runs of one scenario
whose parameters — and, optionally, the link's latency — are drawn from its
parameter space, and keeps whatever goes wrong. Modules, along the seams:

* ``spec``: the campaign spec (YAML), its validation, the campaign id, ``--shard i/N``;
* ``sampling``: episode seeds, random and guided draws (cem, mutate), the score;
* ``episode``: one episode in a pool worker (its own simulator and target);
* ``campaign``: the process pool, generations, resume, stop on SIGTERM/Ctrl-C;
* ``db``: ``campaign.sqlite`` (campaign, shards, episodes, cases);
* ``merge``: the shards of one campaign as one result;
* ``summary`` / ``report``: ``summary.json`` and the self-contained ``report.html``;
* ``progress`` / ``cli``: the live display and the command line.

Nothing here imports MuJoCo at module level: pool workers choose the GL backend
first.
"""
