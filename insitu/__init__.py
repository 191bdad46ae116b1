"""minority's in situ API: publish a running simulation's particles to the render server
from the simulation's own time loop, the way the spec asks, without ever blocking it.

    import minority.insitu

    with minority.insitu.connect("column", rank=0, ranks=1,
                                 connect=("tcp/127.0.0.1:7447",), record=None) as viz:
        for step in range(steps):
            time_s = advance()                    # your solver: simulated time after the step, s
            if viz.due(step, time_s):             # at every step, step 0 included
                viz.publish(step, time_s, x,      # positions [n, 3] m
                            fields={"velocity": v, "displacement": x - x0},  # [n] or [n, k]
                            spacing_m=0.01)       # particle spacing, m

`connect(run, rank=0, ranks=1, connect=("tcp/127.0.0.1:7447",), record=None, spec=None,
wait_s=0.0, *, id_offset=0, particles=None, options=None, ...)` opens a zenoh client
session, declares the rank's liveliness token (the server knows the rank is alive), fetches
the run's spec from the server (`spec`: a spec file to follow when no server serves one),
follows its updates, and starts one sender thread. No server is not an error: the loop runs
on, publishing nothing; `record` (an MCAP path) keeps what would have been sent, with or
without a server. Ranks are numbered by hand; mpi4py is not needed.

`viz.due(step, time_s)` says at once (microseconds) whether a view of the spec is due at
that step, or the Stats cadence (every 5 ms of simulated time), so the loop builds fields
only then; `viz.wanted` names the fields the due step needs. `viz.publish(step, time_s,
positions, fields=..., ids=None, spacing_m=..., bounds_m=None)` culls to the spec's regions
(with the particles outside them sent once, for the server's cache, and again only when
they move), its views' fields, decimation and occlusion culling: the caller's thread only
copies what the step needs, the sender thread culls, encodes and puts; it never waits on
the network (with the sender behind, a full outbox refuses the step at once, counted). Bad input
raises ValueError before anything is sent. `publish(..., copy=False)` lends the arrays
instead (insitu.lend): nothing is copied, the sender reads them in place (fields may be
functions it calls), and `viz.reclaim()` waits until it has, before the caller changes
them; a bad lent step raises at the next call. `viz.close(detail=None)` drains the outbox,
sends the `rank_done` event with the counts and returns them (`PublishStats`); `with` does
it, and publishes an exception raised in the loop as an `error` event first.

Inside: insitu.publisher (RankPublisher: spec, cadences, culling, Stats), insitu.sender (the
sender thread: puts, stalls, checkpoints, the record), insitu.outbox, insitu.payload (what a
chunk and a Stats message carry), insitu.context (the server's cache of particles outside
the regions), insitu.visibility (occlusion culling), insitu.lend (lent steps). docs/insitu.md is the guide.
"""

from minority.insitu.api import InSitu, connect
from minority.insitu.payload import Particles
from minority.insitu.publisher import PublishOptions, PublishStats

__all__ = ["InSitu", "Particles", "PublishOptions", "PublishStats", "connect"]
