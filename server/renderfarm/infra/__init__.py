"""Outside the process: the PostgreSQL store and its migrations, the embedded database, image
files, the tile cache's spill files, the spool, settings from the environment, and the worker
binary's scene check. Imports domain only (never app, api or cli)."""
