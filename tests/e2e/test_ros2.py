

def test_bench_service_times_the_ros2_service(ros2_server: ServerProcess) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "agilegs.service.cli", "bench", "service", "--url",
         ros2_server.url, "--zenoh", ros2_server.zenoh_endpoint, "--ros2", DEMO_NS,
         "--requests", "5", "--warmup", "1", "--pool", "30", "--max-gaussians", "100",
         "--size", "16", "--clients", "1", "--selections", "1"],
        capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    row = next(line for line in proc.stdout.splitlines() if line.startswith("ros2/preset"))
    assert float(row.split()[1]) > 0  # the overhead's p50, in ms
