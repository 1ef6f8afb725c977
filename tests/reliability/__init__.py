"""The reliability suite: each guarantee of the README's reliability section, shown against real
processes (redis-server, ``hmcc serve``, ``hmcc worker``) on loopback, every wait bounded."""
