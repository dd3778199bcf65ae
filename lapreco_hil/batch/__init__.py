"""Batch evaluation of a folder of sessions (``lapreco batch``, run by lapreco_hil.app.batch on Ray): which
folders are sessions, one row per session read back from its output folder, and the table and plots across
sessions. Nothing here imports Ray."""
