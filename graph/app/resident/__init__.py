"""A warm resident process that serves ``acinoset solve`` from a shell, as a build daemon serves builds.

Why. A new Python process pays about a second before it solves anything: importing numba and
gtsam, and numba's first load of its cached kernels in that process. The solve of a 150-frame run
takes a fifth of that. A process that has paid it once, and forks a child per solve (as the job
service's workers do), starts each solve at once.

Lifecycle.

* ``acinoset solve`` (the *client*) looks for the resident of its *key* and hands the solve over.
* If there is none, it solves in its own process as before, then starts one: ``python -c``
  :func:`graph.app.resident.server.serve`, detached (a new session, stdin/stdout/stderr on /dev/null, every other
  inherited file closed), so that a shell pipeline or a CI job never waits for it.
* The resident imports the solver, runs tiny solves (:func:`graph.app.warmup.warm_up`, and one tiny
  ``acinoset solve`` from files to files) so that its kernels and the command's readers and
  writers are loaded, then listens. It exits after ``ACINOSET_RESIDENT_IDLE`` seconds without a solve (default
  600), on SIGTERM (``acinoset resident stop``; a solve being served finishes first), or when the
  installed code changes. ``ACINOSET_RESIDENT=0`` turns it off: every solve runs in its own process.

Where. ``$XDG_RUNTIME_DIR/acinoset``, else ``$XDG_CACHE_HOME/acinoset/resident`` (``~/.cache``): a
directory of mode 0700 owned by the user (anything else and the client solves in its own process).
Per key: ``KEY.sock`` (the socket), ``KEY.lock`` (held with ``flock`` for the resident's whole life,
so two clients starting at once start one resident; it holds the resident's pid and counts as
JSON) and ``KEY.log`` (one line per solve served).

The key. A hash of the package version, the Python executable (path, size, mtime), every file of
the ``graph`` package (path, size, mtime), the mtime of each ``site-packages`` directory on
``sys.path`` (an install or upgrade changes it) and the environment variables that change what is
imported or compiled (:data:`KEY_ENV_PREFIXES`: ``NUMBA_*``, thread counts, ``PYTHON*``,
``ACINOSET_*`` ...). An edited or upgraded install has a new key: its first solve starts a new
resident and the old one idles out (it also checks its own key each minute and leaves when it changed).

Protocol: one Unix stream connection per solve.

1. client -> resident: an 8-byte big-endian length and a JSON object ``{argv, cwd, env, umask,
   entry, commands}`` (``entry``: the command line's ``main`` as ``module:function``, one of
   :data:`ENTRIES`; ``commands``: the :class:`graph.app.cli.Command` table it is called with).
2. The resident hands the connection to a child: the one it forked ahead while no solve ran (it
   waits on a socket pair for the connection; a fork of the resident takes 5-7 ms), or, when
   solves overlap, one forked on the spot. The child reads the request, enters ``cwd``, takes
   ``env`` and ``umask``, and answers ``pid N\\n`` (``fail\\n`` if any of that failed).
3. client -> child: ``go\\n`` with the client's file descriptors 0, 1, 2 attached (``SCM_RIGHTS``;
   sent only now, so that none waits in a hung resident's queue holding the client's pipes open);
   the child makes them its own 0, 1, 2 and answers ``run\\n``: from then on the solve is the
   child's. A child that gets no ``go`` (the client gave up waiting) exits having done nothing, and
   a client that gets no ``run`` solves in its own process.
4. The child runs ``entry(argv, commands)``, exactly what the client would have run, sends
   ``exit S\\n`` with its status and exits with it (the client need not wait for the teardown of a
   large process: 5-10 ms). The resident reaps it and sends the same line, or ``signal N\\n`` if it
   was killed before it could; the client takes the first line and exits the same way
   (re-raising the signal on itself).

Ctrl-C and SIGTERM/SIGHUP/SIGQUIT sent to the client are forwarded to the child's pid (held until
the child has said ``run``, and held blocked in the child from then until its solve's own handlers
are in place: one that comes at once ends the solve as 'interrupted', never lost); Ctrl-Z
(SIGTSTP) stops the child with the client, and SIGCONT resumes both. A client that dies without a
word (SIGKILL, a crashed shell) ends its child too: the child watches its connection and, when the
client's end closes before the solve has, kills itself as the client was killed. Anything that
fails before ``run`` makes the client solve in its own process: a resident never makes a solve fail.
The client's side imports nothing heavy (no numpy, numba or gtsam).

The modules: :mod:`.protocol` (the key, the files, the limits and the framing both sides share),
:mod:`.client` (the hand-over), :mod:`.server` (the resident and its children) and :mod:`.status`
(``acinoset resident status|stop``).
"""
