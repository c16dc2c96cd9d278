#!/usr/bin/env python3
"""Watches every Robot of a namespace and writes each change, stamped with the time it arrived, to
a file: `<unix time>|<event type>|<name>|<phase>|<gateway>|<connected>|<written>`, where
`<written>` is the unix time of the object's latest write as the API server recorded it (the
newest `metadata.managedFields[].time`; empty if it has none). A reader whose watch runs late
(an API server busy relisting after a restart) can so judge its view at the moment it shows,
not at the moment it arrived.

It reads the API server's watch stream (newline-delimited JSON) through `curl --no-buffer`:
`kubectl get --watch` buffers its output to a pipe in 8 KiB blocks, and Python's own HTTP client
holds back the last chunk of a chunked response until the next one comes, so both would stamp
changes late. Standard library and curl only.

Usage: recovery_watch.py API_URL CA_FILE TOKEN_FILE NAMESPACE OUT_FILE (runs until killed;
bench/recovery.sh starts it)."""
import calendar
import json
import os
import subprocess
import sys
import time


def token_header(token_file):
    """A file holding the Authorization header, so the token is not on curl's command line."""
    path = token_file + ".header"
    with open(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as out:
        out.write("Authorization: Bearer %s\n" % open(token_file).read().strip())
    return path


def written(obj):
    """The unix time of `obj`'s latest write (its newest managed-fields entry), or None."""
    times = [m.get("time") for m in obj.get("metadata", {}).get("managedFields") or []]
    times = [t for t in times if t]
    if not times:
        return None
    # RFC 3339 in UTC with whole seconds ("2026-12-07T00:48:52Z"), as the API server writes it.
    return calendar.timegm(time.strptime(max(times), "%Y-%m-%dT%H:%M:%SZ"))


def line(obj, kind):
    """One output line for `obj` as an event of type `kind`."""
    status = obj.get("status") or {}
    at = written(obj)
    return "%.3f|%s|%s|%s|%s|%s|%s\n" % (
        time.time(), kind, obj.get("metadata", {}).get("name", ""),
        status.get("phase", ""), status.get("gateway", ""),
        "true" if status.get("connected") else "false", "" if at is None else at)


def list_robots(collection, ca, header, out):
    """Lists every Robot whole from the API server's cache (`resourceVersion=0`), writes each as
    an ADDED line and returns the list's resourceVersion, where the watch then starts; None if
    the API server did not answer. Not in pages: a paged list is read from etcd, which took
    minutes for 10,000 Robots after an API server restart, and the view stood still meanwhile."""
    got = subprocess.run(["curl", "-sS", "--fail", "--max-time", "120", "--cacert", ca,
                          "-H", "@" + header, collection + "?resourceVersion=0"],
                         capture_output=True)
    if got.returncode != 0:
        print("list failed (curl exit %s): %s" % (got.returncode, got.stderr[:200]),
              file=sys.stderr)
        return None
    try:
        listing = json.loads(got.stdout)
    except ValueError:
        return None
    for obj in listing.get("items", []):
        out.write(line(obj, "ADDED"))
    return listing.get("metadata", {}).get("resourceVersion")


def main():
    api, ca, token_file, namespace, out_path = sys.argv[1:6]
    collection = f"{api}/apis/fleet.lekiwi.io/v1alpha1/namespaces/{namespace}/robots"
    base = collection + "?watch=1&allowWatchBookmarks=true&timeoutSeconds=50"
    header = token_header(token_file)
    version = None
    with open(out_path, "w", buffering=1) as out:
        while True:
            # At the start, and after a version too old (410): list, and write what the list
            # holds as ADDED lines (the report reads them as states, not changes), then watch
            # from the list's own version. (A watch without a version would do both, but its
            # ADDED objects carry their own, older versions: resuming from one of them after a
            # stream that ended early would miss changes.)
            if version is None:
                version = list_robots(collection, ca, header, out)
                if version is None:
                    time.sleep(1)
                    continue
            url = base + f"&resourceVersion={version}"
            # The server ends each watch within 50 s (after a bookmark of where it stood), and
            # curl gives up on one that brings nothing for 60 s: a request an API server took in
            # while it restarted may never be answered, and must not blind the watch for good.
            # An error answer (a restarting server's 503, say) ends curl (--fail), not the watch.
            curl = ["curl", "-sS", "--fail", "--no-buffer", "--max-time", "120", "--speed-time", "60",
                    "--speed-limit", "1", "--cacert", ca, "-H", "@" + header, url]
            with subprocess.Popen(curl, stdout=subprocess.PIPE) as proc:
                for raw in proc.stdout:
                    try:
                        event = json.loads(raw)
                    except ValueError:
                        print("not a watch event: %r" % raw[:200], file=sys.stderr)
                        proc.kill()
                        break
                    obj = event.get("object", {})
                    if event.get("type") == "ERROR":
                        print("watch error: %s" % obj.get("message"), file=sys.stderr)
                        version = None
                        proc.kill()
                        break
                    version = obj.get("metadata", {}).get("resourceVersion", version)
                    if event.get("type") == "BOOKMARK":
                        continue
                    out.write(line(obj, event.get("type", "")))
            print("%.3f watch stream ended (curl exit %s); resuming" % (time.time(), proc.returncode),
                  file=sys.stderr)
            if proc.returncode == 22:
                # An HTTP error (410 for a version too old among them): start over with a list.
                version = None
            time.sleep(0.5)


if __name__ == "__main__":
    main()
