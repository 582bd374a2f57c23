"""Many sessions, one map: each log is a session run on its own (Ray workers), then the
sessions are matched against each other (cross-session loops), joined where enough verified
loops agree, solved as one robust pose graph and written as one merged map.

Modules, in the order `map` uses them: `workers` (Ray: shared codebooks, sessions),
`session_map` (a finished session as the merge reads it), `cross_loops` (one session's
keyframes against the other sessions' places), `linking` (which sessions join, and where),
`merged_graph` (the multi-session pose graph), `evaluation` (against one world's ground
truth), `writer` (the merged map folder), `runner` (the command).
"""
