"""The index's tables: every row the archive keeps, on one ``MetaData``.

``repository.index`` answers the archive's questions from them, ``repository.accounts``
and ``repository.reservations`` keep theirs, ``repository.evaluation_index`` keeps the
evaluations; ``repository.migrate`` upgrades them. SQLite and PostgreSQL get the same
tables (``metadata.create_all``).
"""

from __future__ import annotations

import sqlalchemy as sa

metadata = sa.MetaData()

meta = sa.Table(
    "labd_meta",
    metadata,
    sa.Column("key", sa.String(64), primary_key=True),
    sa.Column("value", sa.String(256), nullable=False),
)

users = sa.Table(
    "users",
    metadata,
    sa.Column("name", sa.String(64), primary_key=True),
    sa.Column("token_sha256", sa.String(64), nullable=False, unique=True),
    sa.Column("created", sa.Float, nullable=False),
    sa.Column("max_running", sa.Integer, nullable=False),
    sa.Column("max_daily", sa.Integer, nullable=False),
    sa.Column("worker", sa.Boolean, nullable=False),  # may claim and file trials (labd worker)
)

# A user's API tokens (any number, each revocable by its owner); only their sha256 is
# kept. A token in ``users.token_sha256`` with no row here is one an older labd made.
tokens = sa.Table(
    "tokens",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("user", sa.String(64), sa.ForeignKey("users.name"), nullable=False),
    sa.Column("sha256", sa.String(64), nullable=False, unique=True),
    sa.Column("label", sa.String(128), nullable=False),
    sa.Column("created", sa.Float, nullable=False),
    sa.Column("revoked", sa.Float),  # when; a revoked token is refused
)

# Signing in on the pages (``repository.accounts``): a password's argon2id hash, and
# each browser session (only the sha256 of its cookie; its forms' CSRF token).
passwords = sa.Table(
    "passwords",
    metadata,
    sa.Column("user", sa.String(64), sa.ForeignKey("users.name"), primary_key=True),
    sa.Column("hash", sa.String(256), nullable=False),
    sa.Column("changed", sa.Float, nullable=False),
)
web_sessions = sa.Table(
    "web_sessions",
    metadata,
    sa.Column("sha256", sa.String(64), primary_key=True),
    sa.Column("user", sa.String(64), sa.ForeignKey("users.name"), nullable=False),
    sa.Column("csrf", sa.String(64), nullable=False),
    sa.Column("created", sa.Float, nullable=False),
    sa.Column("expires", sa.Float, nullable=False),
)

# People an OpenID provider vouches for (``repository.accounts``): an account is found by
# the provider's issuer and its subject, never by e-mail (an address may change hands);
# the e-mail is what the provider said at the last sign-in, for the operator to read.
identities = sa.Table(
    "identities",
    metadata,
    sa.Column("issuer", sa.String(1024), primary_key=True),
    sa.Column("subject", sa.String(255), primary_key=True),
    sa.Column("user", sa.String(64), sa.ForeignKey("users.name"), nullable=False, index=True),
    sa.Column("email", sa.String(320), nullable=False),
    sa.Column("created", sa.Float, nullable=False),
    sa.Column("last", sa.Float, nullable=False),  # the last sign-in through it
)

# Live robots booked for a slot (``repository.reservations``). ``end`` is when the slot
# ends now: an early release moves it to the release (to ``start`` before it began).
# The slot's key is derived from the lab's secret and ``nonce``; nothing here reveals it.
reservations = sa.Table(
    "reservations",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("robot", sa.String(64), nullable=False),
    sa.Column("user", sa.String(64), sa.ForeignKey("users.name"), nullable=False),
    sa.Column("start", sa.Float, nullable=False),
    sa.Column("end", sa.Float, nullable=False),
    sa.Column("booked_end", sa.Float, nullable=False),  # the end as booked or extended
    sa.Column("created", sa.Float, nullable=False),
    sa.Column("released", sa.Float),
    sa.Column("nonce", sa.String(32), nullable=False),
)
sa.Index("ix_reservations_robot", reservations.c.robot, reservations.c.start)
sa.Index("ix_reservations_user", reservations.c.user, reservations.c.start)
sa.Index("ix_tokens_user", tokens.c.user)
sa.Index("ix_web_sessions_user", web_sessions.c.user)

trials = sa.Table(
    "trials",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("kind", sa.String(16), nullable=False),
    # what was asked
    sa.Column("repository", sa.String(2048), nullable=False),
    sa.Column("ref", sa.String(256)),
    sa.Column("commit", sa.String(40), nullable=False),
    sa.Column("task", sa.String(64), nullable=False),
    sa.Column("params", sa.JSON, nullable=False),
    sa.Column("seed", sa.BigInteger, nullable=False),
    sa.Column("submitter", sa.String(64), nullable=False),
    sa.Column("public", sa.Boolean, nullable=False),
    sa.Column("rerun_of", sa.Integer, sa.ForeignKey("trials.id")),
    sa.Column("data", sa.JSON),  # the archived records it learns from, pinned (PinnedRecord)
    # a match's leg: the team at away; the code above is home's (schema 4)
    sa.Column("away_repository", sa.String(2048)),
    sa.Column("away_ref", sa.String(256)),
    sa.Column("away_commit", sa.String(40)),
    sa.Column("step_deadline", sa.Float),  # seconds a team may take to step
    # the queue
    sa.Column("status", sa.String(16), nullable=False),
    sa.Column("outcome", sa.String(16)),  # finished trials only
    sa.Column("reason", sa.Text, nullable=False),
    # an error of the lab's making, not the controller's (schema 3)
    sa.Column("lab_fault", sa.Boolean, nullable=False, default=False, server_default=sa.false()),
    sa.Column("created", sa.Float, nullable=False),
    sa.Column("started", sa.Float),
    sa.Column("finished", sa.Float),
    sa.Column("worker", sa.String(128)),
    sa.Column("lease_until", sa.Float),
    sa.Column("attempts", sa.Integer, nullable=False),
    sa.Column("cancel_requested", sa.Boolean, nullable=False),
    # what came out
    sa.Column("manifest", sa.JSON),
    sa.Column("manifest_digest", sa.String(64)),
    sa.Column("data_digest", sa.String(64)),
    sa.Column("digest_topics", sa.JSON),
    sa.Column("metrics", sa.JSON),
    sa.Column("reward", sa.Float),  # metrics' reward, as a column to sort and rank by
    sa.Column("backend", sa.String(16)),
    sa.Column("wall_seconds", sa.Float),
    sa.Column("mcap", sa.String(71)),  # blob digests, "sha256:..."
    sa.Column("mcap_size", sa.BigInteger),
    sa.Column("stdout", sa.String(71)),
    sa.Column("stderr", sa.String(71)),
    sa.Column("reproduced", sa.Boolean),  # reruns only: identical data digest
    sa.Column("divergence", sa.Text),  # reruns that did not reproduce: where they parted
    sa.Column("signature", sa.JSON),  # the lab's signature of the filed record (signing.py)
)

# Derived artifacts of a record (a summary for its page, an export, a rendered video):
# blobs beside the record, never part of its digests, made again at will.
derived = sa.Table(
    "derived",
    metadata,
    sa.Column("trial_id", sa.Integer, sa.ForeignKey("trials.id"), primary_key=True),
    sa.Column("name", sa.String(64), primary_key=True),  # e.g. summary.json, export.parquet
    sa.Column("digest", sa.String(71), nullable=False),
    sa.Column("size", sa.BigInteger, nullable=False),
    sa.Column("media_type", sa.String(128), nullable=False),
    sa.Column("created", sa.Float, nullable=False),
)

# Every list is newest first, so each filter has an index ending in id.
sa.Index("ix_trials_repository", trials.c.repository, trials.c.id)
sa.Index("ix_trials_commit", trials.c.commit, trials.c.id)
sa.Index("ix_trials_task", trials.c.task, trials.c.id)
sa.Index("ix_trials_task_status", trials.c.task, trials.c.status, trials.c.id)
sa.Index("ix_trials_status", trials.c.status, trials.c.id)
sa.Index("ix_trials_outcome", trials.c.outcome, trials.c.id)
sa.Index("ix_trials_task_outcome", trials.c.task, trials.c.outcome, trials.c.id)
sa.Index("ix_trials_kind", trials.c.kind, trials.c.id)
sa.Index("ix_trials_task_reward", trials.c.task, trials.c.reward, trials.c.id)
sa.Index("ix_trials_reward", trials.c.reward, trials.c.id)
sa.Index("ix_trials_submitter", trials.c.submitter, trials.c.id)
sa.Index("ix_trials_created", trials.c.created)
sa.Index("ix_trials_rerun_of", trials.c.rerun_of)
sa.Index("ix_trials_away_commit", trials.c.away_commit, trials.c.id)
# Claiming: the oldest queued trial of each submitter, public ones first.
sa.Index("ix_trials_queue", trials.c.status, trials.c.public, trials.c.submitter, trials.c.id)
# Serving a blob: the trials (and derived artifacts) that hold it, whose readers may read it.
sa.Index("ix_trials_mcap", trials.c.mcap)
sa.Index("ix_trials_stdout", trials.c.stdout)
sa.Index("ix_trials_stderr", trials.c.stderr)
sa.Index("ix_derived_digest", derived.c.digest)

# Evaluations (``repository.evaluation``): one commit on one suite of a task; each of its
# episodes is a trial of ``trials``. ``hidden`` marks the trials of a held-out suite
# version not yet retired: their seeds and records are the operator's alone.
evaluations = sa.Table(
    "evaluations",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("task", sa.String(64), nullable=False),
    sa.Column("task_version", sa.String(32), nullable=False),
    sa.Column("suite", sa.String(32), nullable=False),
    sa.Column("suite_version", sa.Integer, nullable=False),
    sa.Column("held_out", sa.Boolean, nullable=False),
    sa.Column("repository", sa.String(2048), nullable=False),
    sa.Column("ref", sa.String(256)),
    sa.Column("commit", sa.String(40), nullable=False),
    sa.Column("params", sa.JSON, nullable=False),
    sa.Column("submitter", sa.String(64), nullable=False),
    sa.Column("rerun_of", sa.Integer, sa.ForeignKey("evaluations.id")),
    sa.Column("created", sa.Float, nullable=False),
    sa.Column("cancel_requested", sa.Boolean, nullable=False),
    sa.Column("finished", sa.Float),  # when its last episode ended
    sa.Column("signature", sa.JSON),  # the lab's, over its episodes (labd.evaluation/2)
)
episodes = sa.Table(
    "evaluation_episodes",
    metadata,
    sa.Column("evaluation_id", sa.Integer, sa.ForeignKey("evaluations.id"), primary_key=True),
    sa.Column("episode", sa.Integer, primary_key=True),  # its place in the suite, from 0
    sa.Column("seed", sa.BigInteger, nullable=False),
    sa.Column("trial_id", sa.Integer, sa.ForeignKey("trials.id"), nullable=False, unique=True),
    sa.Column("hidden", sa.Boolean, nullable=False),
)
# Held-out suite versions the operator retired: their episodes are public from then on.
retired_suites = sa.Table(
    "retired_suites",
    metadata,
    sa.Column("task", sa.String(64), primary_key=True),
    sa.Column("suite", sa.String(32), primary_key=True),
    sa.Column("version", sa.Integer, primary_key=True),
    sa.Column("retired", sa.Float, nullable=False),
)
sa.Index(
    "ix_evaluations_suite",
    evaluations.c.task,
    evaluations.c.suite,
    evaluations.c.suite_version,
    evaluations.c.id,
)
sa.Index("ix_evaluations_commit", evaluations.c.commit, evaluations.c.id)
sa.Index("ix_evaluations_repository", evaluations.c.repository, evaluations.c.id)
sa.Index("ix_evaluations_submitter", evaluations.c.submitter, evaluations.c.id)

# Matches (``repository.match``): two commits, A and B, play a task's seeds, each seed
# twice with the sides swapped; each leg is a trial of ``trials`` (kind ``match``) whose
# own code plays home and whose ``away_*`` team plays away. What a match adds up to is
# read from its legs' trials whenever it is asked for; the lab signs it once the last
# leg has ended (schema 4).
matches = sa.Table(
    "matches",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("task", sa.String(64), nullable=False),
    sa.Column("task_version", sa.String(32), nullable=False),
    sa.Column("params", sa.JSON, nullable=False),
    sa.Column("a_repository", sa.String(2048), nullable=False),
    sa.Column("a_ref", sa.String(256)),
    sa.Column("a_commit", sa.String(40), nullable=False),
    sa.Column("b_repository", sa.String(2048), nullable=False),
    sa.Column("b_ref", sa.String(256)),
    sa.Column("b_commit", sa.String(40), nullable=False),
    sa.Column("step_deadline", sa.Float, nullable=False),  # seconds a team may take to step
    sa.Column("submitter", sa.String(64), nullable=False),
    sa.Column("created", sa.Float, nullable=False),
    sa.Column("cancel_requested", sa.Boolean, nullable=False),
    sa.Column("finished", sa.Float),  # when its last leg ended
    sa.Column("signature", sa.JSON),  # the lab's, over its legs
)
match_legs = sa.Table(
    "match_legs",
    metadata,
    sa.Column("match_id", sa.Integer, sa.ForeignKey("matches.id"), primary_key=True),
    sa.Column("leg", sa.Integer, primary_key=True),  # its place in the match, from 0
    sa.Column("seed", sa.BigInteger, nullable=False),
    sa.Column("home", sa.String(1), nullable=False),  # "a" or "b": who played home
    sa.Column("trial_id", sa.Integer, sa.ForeignKey("trials.id"), nullable=False, unique=True),
)
sa.Index("ix_matches_task", matches.c.task, matches.c.id)
sa.Index("ix_matches_a_commit", matches.c.a_commit, matches.c.id)
sa.Index("ix_matches_b_commit", matches.c.b_commit, matches.c.id)
sa.Index("ix_matches_submitter", matches.c.submitter, matches.c.id)

# The commits entered on a task's ladder (``labd ladder join``): the lab schedules their
# matches against opponents of near rating and those with few matches (schema 4).
ladder_entries = sa.Table(
    "ladder_entries",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("task", sa.String(64), nullable=False),
    sa.Column("repository", sa.String(2048), nullable=False),
    sa.Column("ref", sa.String(256)),
    sa.Column("commit", sa.String(40), nullable=False),
    sa.Column("public", sa.Boolean, nullable=False),
    sa.Column("submitter", sa.String(64), nullable=False),
    sa.Column("created", sa.Float, nullable=False),
)
sa.Index("ix_ladder_entries_task", ladder_entries.c.task, ladder_entries.c.id)
sa.Index("ix_ladder_entries_submitter", ladder_entries.c.submitter, ladder_entries.c.created)

# Benchmark runs (``repository.benchmark_run``): one commit evaluated on every task of a
# benchmark; each task's evaluation is a row of ``evaluations`` (schema 4).
benchmark_runs = sa.Table(
    "benchmark_runs",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("benchmark", sa.String(64), nullable=False),
    sa.Column("suite", sa.String(32), nullable=False),
    sa.Column("repository", sa.String(2048), nullable=False),
    sa.Column("ref", sa.String(256)),
    sa.Column("commit", sa.String(40), nullable=False),
    sa.Column("submitter", sa.String(64), nullable=False),
    sa.Column("created", sa.Float, nullable=False),
    sa.Column("finished", sa.Float),  # when its last evaluation ended
    sa.Column("signature", sa.JSON),  # the lab's, over its evaluations' signatures
)
benchmark_run_evaluations = sa.Table(
    "benchmark_run_evaluations",
    metadata,
    sa.Column("run_id", sa.Integer, sa.ForeignKey("benchmark_runs.id"), primary_key=True),
    sa.Column("place", sa.Integer, primary_key=True),  # the task's place in the benchmark
    sa.Column("task", sa.String(64), nullable=False),
    sa.Column(
        "evaluation_id", sa.Integer, sa.ForeignKey("evaluations.id"), nullable=False, unique=True
    ),
)
sa.Index("ix_benchmark_runs_benchmark", benchmark_runs.c.benchmark, benchmark_runs.c.id)
sa.Index("ix_benchmark_runs_commit", benchmark_runs.c.commit, benchmark_runs.c.id)
