"""MPI spatial domain decomposition of a DEM run: one `Simulation` per rank, halos of ghosts.

Each rank owns the particles of its subdomain (recursive bisection of the particle box along
its longest axis not along gravity, or any ``owner(x) -> ranks`` the caller passes, e.g. the
FE partition) and holds, as GHOST particles of its local `dem.Simulation`, copies of the
other ranks' particles within ``2 r_max + halo_skin`` of its owned particles' box. The n
steps of a call run in one call of the local `Simulation.step` (its fused kick + drift
pass, no per-step Python set-up); its hook, after each force pass, has the owners send x,
v, omega of the copies *as the coming half-kicks and drift will make them* (one
``Alltoallv`` of a contiguous buffer, whose header rows also carry each rank's largest
coming displacement, so it is the step's only synchronisation); a GHOST keeps its
prescribed state through the step, so the local run's force pass sees the same neighbours
as the serial one. A pair of an owned particle and a copy is computed on both ranks from
identical data, each rank integrating its own copy of the pair's tangential history. On
one rank nothing is exchanged: the run is the local `Simulation`.

Why the result equals the serial run to round-off (in practice bit for bit): the local arrays
are kept in global-id order, so local pairs (i < j) sort as the serial ones; every contact of
an owned particle is in the local list; the pair loop sums onto particles in pair order. An
owned particle so sees the same contacts, in the same order, with the same data.

Ownership is fixed between *decompositions*; one happens when some particle would move more
than ``halo_skin / 2`` since the last one (so no pair outside the halo can have closed). A
decomposition migrates particles to their new owners with the forces of the last step and
their contact history, keyed by global ids: a pair's history is authoritative on the owner
of its lower-id particle, which sends it to both new owners.

Prescribed GHOST motions (``step(prescribed=...)``, rows by global id) are packed once per
call and written by every rank into the copies it holds, owned and halo, with the
coefficients of the call's step (a call split into local calls writes the serial bits); the
first step's state is written before the halo exchange, so that a jump of the motion is seen
by the displacement criterion and a decomposition. ``decay`` damps the owned FREE particles
in the local run, and the halo prediction applies it where the integrator does.

Walls are the same on every rank (each local run carries a copy and advances it with the
wall's velocity); a rank's wall force is its owned particles' share. `wall_forces` sums
the shares in rank order (the same bits on every rank and every run), and a ``hook`` of
`step` runs on every rank after each force pass, as `Simulation.step`'s: a `dem.ServoWall`
there reads the summed force and sets the same velocity on every rank (`dem.relax` with
controllers). The sum differs from the serial run's by round-off (another order).

The energy ledger (`DistributedSimulation.energy`) books every term once: a particle's
kinetic energy and works on its owner, a pair's elastic energy and the change of its
spring energy on the owner of its lower id, a wall contact on the particle's owner (a halo
copy has no wall contacts, nor contacts with other copies: the local lists drop them).

`DistributedSimulation.from_simulation` continues a serial `dem.Simulation` held, the same
to the bit, on every rank (e.g. a coupled run's DE window consolidated serially, then pushed
over the ranks): the first decomposition takes each rank's id block of its rows, with their
forces and the contact history of the block's pairs and wall contacts, routed to the new
owners of both particles as a migration routes it; the walls, time, external forces and the
ledger's sums so far come along.

mpi4py is imported lazily (``import dem`` stays free of MPI); every public method of
`DistributedSimulation` is collective.

The package's rooms: `bisection` (the default owners), `ranks` (collective helpers:
rows exchanged, sums in rank order, errors agreed), `local_run` (a rank's `Simulation` of
owned particles and halo copies, the rows particles and contact history travel in),
`decomposition` (owners, migration, halos and the halo exchange of every step), `results`
(the collective read-outs and the ledger summed over the ranks) and `simulation`
(`DistributedSimulation`: set-up, stepping, external forces, state, checks).
"""

from dem.parallel.bisection import RecursiveBisection
from dem.parallel.simulation import DistributedSimulation

__all__ = ["DistributedSimulation", "RecursiveBisection"]
