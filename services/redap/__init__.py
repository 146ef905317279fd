"""The depot as a Rerun catalog server: `rerun.cloud.v1alpha1.RerunCloudService` ("redap") on the
gRPC port, so Rerun's own viewer browses the fleet and its SDK queries runs as dataframes.

A dataset is an application id (its runs share an entity layout), a segment is a run. Everything
answered is something the depot already holds: catalog rows, chunk indexes, footer manifests and
chunk bytes by range; the client does the querying. docs/catalog-server.md has the map.
"""
