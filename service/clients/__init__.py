"""The clients of the service, apart from the servers: the REST client (``rest``), the gRPC client
(``grpc_client``) and the batch flow of ``geomatch submit`` (``submit``) with its gRPC
implementation (``grpc_submit``).

Nothing here imports the server side; the gRPC client reads only the generated messages
(``service.grpcapi.pb``), which both ends share.
"""
