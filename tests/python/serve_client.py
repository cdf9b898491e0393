"""An outside peer of `geocal serve`: submit a plan (a HIL run in tests/real_time/daemon/api.rs) with `requests`, follow the job on the
event stream and the job route, fetch its results and session, and check what came back."""

import json
import sys
import time

import requests


def main() -> int:
    url, plan_path = sys.argv[1], sys.argv[2]
    with open(plan_path, "rb") as f:
        plan = f.read()
    r = requests.post(f"{url}/v1/jobs", data=plan,
                      headers={"Content-Type": "application/toml"}, timeout=60)
    assert r.status_code == 201, (r.status_code, r.text)
    job_id = r.json()["id"]

    # Follow on the event stream until the job ends (it may have ended before we listen).
    states = []
    with requests.get(f"{url}/v1/events", stream=True, timeout=600) as events:
        job = requests.get(f"{url}/v1/jobs/{job_id}", timeout=60).json()
        if job["state"] in ("queued", "running"):
            name = None
            for line in events.iter_lines(decode_unicode=True):
                if line.startswith("event:"):
                    name = line[len("event:"):].strip()
                elif line.startswith("data:"):
                    data = json.loads(line[len("data:"):])
                    if name == "job" and data["id"] == job_id:
                        states.append(data["state"])
                        if data["state"] in ("succeeded", "failed", "cancelled"):
                            break
    deadline = time.time() + 600
    while True:
        job = requests.get(f"{url}/v1/jobs/{job_id}", timeout=60).json()
        if job["state"] not in ("queued", "running"):
            break
        assert time.time() < deadline, job
        time.sleep(0.1)
    assert job["state"] == "succeeded", job
    assert job["progress"]["done"] == job["progress"]["total"] > 0, job

    results = requests.get(f"{url}/v1/jobs/{job_id}/results", timeout=60)
    assert results.status_code == 200
    results = results.json()
    assert results["format"] == "geocal-results/1", results.get("format")
    assert results["kind"] == "multilateration"
    session = requests.get(f"{url}/v1/jobs/{job_id}/session", timeout=60).content
    assert session[:8] == b"\x89MCAP0\r\n", session[:8]
    listed = {f["name"]: f for f in job["files"]}
    assert listed["session.mcap"]["bytes"] == len(session)

    missing = requests.get(f"{url}/v1/jobs/999999", timeout=60)
    assert missing.status_code == 404 and "error" in missing.json()
    bad = requests.post(f"{url}/v1/jobs", data=b"kind = [", timeout=60,
                        headers={"Content-Type": "application/toml"})
    assert bad.status_code == 400 and "error" in bad.json()
    print(f"job {job_id} succeeded; events {states}; chi2/dof {results['chi2_per_dof']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
