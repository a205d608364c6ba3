"""NodeODM's REST API over the service's use cases: geomatch as a processing node that WebODM adds
in one form (host, port, token), that PyODM scripts drive unchanged and ClusterODM spreads tasks
over. A task is a project plus its match and reconstruct jobs; its results are the model's
``odm`` export (geomatch.export.odm) with the task's console output (docs/webodm.md)."""
