"""How the ranks meet: the process group over gloo, rank info and seeds, object collectives, and ``Comm``
(``collectives.py``), which carries every collective of training through the ranks' shared memory (``shm_allreduce``,
``host_first``) where it can and through gloo where it cannot, and says which.

May import: errors, procfs. Besides them, torch and the standard library only.
"""
