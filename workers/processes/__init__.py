"""Local helper processes of a job (``python -m`` children of the job's process, see :mod:`.children`).

- :mod:`.audit_beside`: the audit stage in a child process while synthesis runs in the job's process;
- :mod:`.partitioned_cpre`: the partitioned ``∃u.CPre`` of the synthesis fixed points in helper processes.
"""
