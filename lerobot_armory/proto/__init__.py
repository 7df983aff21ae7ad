"""Wire protocol (protobuf) between robots and the server: added with the server."""
