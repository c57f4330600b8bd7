"""The farm's tables in PostgreSQL, made and migrated by the servers themselves.

Each migration is applied once, in order, in one transaction that holds an advisory lock
(two nodes starting together migrate once). A node refuses a database whose schema is
newer than it knows: it would misread tables it does not know how to write.
"""

from __future__ import annotations

from typing import Any

from repetrel_host.errors import ConfigError

_LOCK = 0x4879_7265_6C46  # the advisory lock held while migrating ("HyrelF")

MIGRATIONS: list[str] = [
    # 1: nodes and their printers, files by content in chunks, jobs with fencing tokens.
    """
    CREATE SEQUENCE fence;
    CREATE TABLE nodes (
        id uuid PRIMARY KEY,
        name text NOT NULL,
        url text,
        version text,
        joined timestamptz NOT NULL DEFAULT now(),
        lease_until timestamptz NOT NULL,
        lost_at timestamptz           -- its lease ran out (NULL: alive)
    );
    CREATE TABLE printers (
        node uuid NOT NULL REFERENCES nodes (id) ON DELETE CASCADE,
        name text NOT NULL,
        caps jsonb NOT NULL,          -- what it has (needs.py)
        loadout text,                 -- its loadout file, for a lint on another node
        state text NOT NULL DEFAULT 'offline',
        held boolean NOT NULL DEFAULT false,
        job bigint,
        updated timestamptz NOT NULL DEFAULT now(),
        PRIMARY KEY (node, name)
    );
    CREATE TABLE files (
        hash text PRIMARY KEY,        -- SHA-256 of the content
        size bigint NOT NULL,
        chunks integer NOT NULL,
        stored timestamptz NOT NULL DEFAULT now()
    );
    CREATE TABLE file_chunks (
        hash text NOT NULL,
        n integer NOT NULL,
        data bytea NOT NULL,
        PRIMARY KEY (hash, n)
    );
    CREATE TABLE jobs (
        id bigserial PRIMARY KEY,
        name text NOT NULL,
        file text NOT NULL REFERENCES files (hash),
        needs jsonb NOT NULL DEFAULT '{}',
        priority integer NOT NULL DEFAULT 0,
        state text NOT NULL DEFAULT 'queued',
        submitted timestamptz NOT NULL DEFAULT now(),
        submitted_by text,
        total_lines integer NOT NULL DEFAULT 0,
        node uuid,                    -- the node that claimed it, and its printer
        printer text,
        fence bigint,                 -- the claim's token: every later write states it
        refused jsonb NOT NULL DEFAULT '{}',  -- "node/printer": why it gave the job back
        claimed timestamptz,
        started timestamptz,
        ended timestamptz,
        updated timestamptz NOT NULL DEFAULT now(),
        lines integer NOT NULL DEFAULT 0,
        last_line integer NOT NULL DEFAULT 0,
        error text,
        report text,
        filament jsonb,
        safe_stop text,
        local_id bigint               -- the job's number on its node
    );
    CREATE INDEX jobs_queued ON jobs (priority DESC, id) WHERE state = 'queued';
    CREATE INDEX jobs_by_node ON jobs (node) WHERE state IN ('claimed', 'printing', 'paused');
    """,
    # 2: a job recovered on the printer that printed it, from a line of its file.
    """
    ALTER TABLE jobs ADD COLUMN from_line integer;  -- the file's line it starts from
    ALTER TABLE jobs ADD COLUMN resumes bigint;     -- the job it resumes
    """,
    # 3: how long a job should take, and when a printing one should end.
    """
    ALTER TABLE jobs ADD COLUMN estimated_time double precision;  -- planned seconds
    ALTER TABLE jobs ADD COLUMN estimate_of text;   -- 'file' (the whole) or 'rest' (from from_line)
    ALTER TABLE jobs ADD COLUMN expected_end timestamptz;  -- a printing job's, as its node sees it
    """,
    # 4: a job resumed once (its rest's number), and only the states states.py knows.
    """
    ALTER TABLE jobs ADD COLUMN resumed_by bigint;  -- the job that prints its rest
    ALTER TABLE jobs ADD CONSTRAINT jobs_state CHECK (state IN ('queued', 'claimed',
        'printing', 'paused', 'completed', 'cancelled', 'failed', 'interrupted', 'resumed'));
    UPDATE jobs SET expected_end = NULL WHERE state <> 'printing';
    """,
    # 5: each printer's pace, learned from its past jobs: the listed estimates use it.
    """
    ALTER TABLE printers ADD COLUMN pace double precision;  -- actual over planned; NULL: none
    """,
    # 6: of a job's planned seconds, its heat waits' (a pace scales the rest, not them).
    """
    ALTER TABLE jobs ADD COLUMN estimated_heating double precision;
    """,
]


async def migrate(connection: Any) -> int:
    """Bring the schema up to date; returns its version. ConfigError for a newer one."""
    async with connection.transaction():
        await connection.execute("SELECT pg_advisory_xact_lock(%s)", (_LOCK,))
        await connection.execute("CREATE TABLE IF NOT EXISTS farm_schema (version integer)")
        row = await (await connection.execute("SELECT max(version) FROM farm_schema")).fetchone()
        version = row[0] or 0
        if version > len(MIGRATIONS):
            raise ConfigError(
                f"the farm database's schema is version {version}, newer than this "
                f"repetrel-host knows ({len(MIGRATIONS)}): upgrade repetrel-host on this node"
            )
        for number in range(version + 1, len(MIGRATIONS) + 1):
            await connection.execute(MIGRATIONS[number - 1])
            await connection.execute("INSERT INTO farm_schema VALUES (%s)", (number,))
    return len(MIGRATIONS)
