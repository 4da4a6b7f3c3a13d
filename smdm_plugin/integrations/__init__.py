"""What every upstream checkout shares (each family's own hooks are in ``families/<name>/``): the
``smdm run`` launcher, the upstream checkouts registry, the ``--sparse*`` options, hook helpers."""
