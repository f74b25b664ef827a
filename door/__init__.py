"""The one door: every file the project reads, writes, replaces or deletes goes through ``door.files``.

The bottom of the house (stdlib only): the environment reads track files through it, the run
machinery writes run folders through it; nothing here knows about either.
"""
