"""What the service must not lose, and the databases that keep it.

* :mod:`server.storage.store` — the storage interface (records, :class:`Store`) and the group-commit
  writer thread both backends use
* :mod:`server.storage.sql` — the SQL both backends share: reads, deletes, upserts, the write queue
* :mod:`server.storage.sqlite` — the embedded backend (SQLite in WAL mode, the default)
* :mod:`server.storage.postgres` — the shared backend (PostgreSQL; session leases for replicas)
"""
