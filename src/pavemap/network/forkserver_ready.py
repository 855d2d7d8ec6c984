"""Imported last by the workers' forkserver (:data:`pavemap.network.workers.WORKER_IMPORTS`), for its side
effect: what the preload left is collected once and frozen (:func:`gc.freeze`).

Frozen, those objects are not walked again, neither by the garbage collections of the workers forked from the
server (each walk would write to, and so copy, pages the forks share) nor by the server's own exit, which
otherwise spends ~1 s in final collections over what torch leaves after the client has gone (a caller
reading the client's output through a pipe waits for that, since the server holds the pipe open).
"""

from pavemap.shutdown import prepare_quick_exit

prepare_quick_exit()
