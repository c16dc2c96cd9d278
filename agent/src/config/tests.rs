//! The configuration's precedence, its errors, and its flags and environment variables kept in
//! step with the file keys (the book's reference page is generated from them).

use clap::Parser;

use super::*;

#[test]
fn flags_override_file_and_file_overrides_defaults() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("agent.yaml");
    std::fs::write(
        &path,
        "gateway: wss://file/agent\nrobotName: from-file\ntelemetryCpuIntervalS: 7\nteleopCommandPorts: [6000, 6001]\n",
    )
    .unwrap();
    let flags = Flags::parse_from([
        "lekiwi-agent",
        "--config",
        path.to_str().unwrap(),
        "--robot-name",
        "kiwi-9",
        "--teleop-video-ports",
        "7000,7001",
        "--mdns",
        "false",
    ]);
    let cfg = Config::load(&flags, "host").unwrap();
    assert_eq!(cfg.gateway, "wss://file/agent");
    assert_eq!(cfg.robot_name, "kiwi-9");
    assert_eq!(cfg.state_dir, PathBuf::from("/var/lib/lekiwi"));
    assert_eq!(cfg.telemetry_cpu_interval_s, 7);
    assert_eq!(cfg.teleop_command_ports, vec![6000, 6001]);
    assert_eq!(cfg.teleop_video_ports, vec![7000, 7001]);
    assert!(!cfg.mdns);
    assert_eq!(cfg.telemetry_memory_interval_s, 10);
}

#[test]
fn drop_ins_override_the_file_in_name_order_and_flags_override_them() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("agent.yaml");
    std::fs::write(
        &path,
        "gateway: wss://lab/agent\nrobotName: from-file\nhealthCommand: lab-check\n",
    )
    .unwrap();
    let drop_ins = dir.path().join("agent.d");
    assert_eq!(drop_in_dir(&path), drop_ins);
    std::fs::create_dir(&drop_ins).unwrap();
    std::fs::write(
        drop_ins.join("50-join.yaml"),
        "gateway: wss://joined/agent\nrobotName: joined\n",
    )
    .unwrap();
    std::fs::write(drop_ins.join("90-local.yaml"), "robotName: local\n").unwrap();
    std::fs::write(drop_ins.join("README"), "not yaml: [").unwrap();
    let flags = Flags::parse_from(["lekiwi-agent", "--config", path.to_str().unwrap()]);
    let cfg = Config::load(&flags, "host").unwrap();
    assert_eq!(cfg.gateway, "wss://joined/agent");
    assert_eq!(cfg.robot_name, "local");
    assert_eq!(cfg.health_command, "lab-check", "the lab's keys stay");
    let flags = Flags::parse_from([
        "lekiwi-agent",
        "--config",
        path.to_str().unwrap(),
        "--robot-name",
        "flag",
    ]);
    assert_eq!(Config::load(&flags, "host").unwrap().robot_name, "flag");
    std::fs::write(drop_ins.join("60-bad.yaml"), "gatewy: typo\n").unwrap();
    let err = Config::load(&flags, "host").unwrap_err().to_string();
    assert!(err.contains("gatewy"), "{err}");
}

#[test]
fn bad_file_and_missing_gateway_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("agent.yaml");
    std::fs::write(&path, "gatewy: typo\n").unwrap();
    let flags = Flags::parse_from(["lekiwi-agent", "--config", path.to_str().unwrap()]);
    let err = Config::load(&flags, "h").unwrap_err().to_string();
    assert!(err.contains("unknown field `gatewy`"), "{err}");

    std::fs::write(
        &path,
        "gateway: ws://127.0.0.1\ntelemetryCpuIntervalS: fast\n",
    )
    .unwrap();
    let err = Config::load(&flags, "h").unwrap_err().to_string();
    assert!(err.contains("invalid type"), "{err}");

    std::fs::write(&path, "gateway: ws://127.0.0.1\nstatusListen: nowhere\n").unwrap();
    let err = Config::load(&flags, "h").unwrap_err().to_string();
    assert!(err.contains("statusListen"), "{err}");

    let flags = Flags::parse_from(["lekiwi-agent", "--config", "/nonexistent/agent.yaml"]);
    let err = Config::load(&flags, "h").unwrap_err().to_string();
    assert!(err.contains("LEKIWI_GATEWAY_URL"), "{err}");
}

/// Every file key (camelCase) with the flag of the same name in kebab case; panics when a
/// key has no flag.
fn keys_and_flags() -> Vec<(String, clap::Arg)> {
    use clap::CommandFactory;
    let cmd = Flags::command();
    let serde_json::Value::Object(keys) = serde_json::to_value(Config::default()).unwrap() else {
        unreachable!()
    };
    // The token itself is never printed, so it is not serialized.
    keys.keys()
        .cloned()
        .chain(["enrollmentToken".to_owned()])
        .map(|key| {
            let kebab: String = key
                .chars()
                .flat_map(|c| {
                    if c.is_ascii_uppercase() {
                        vec!['-', c.to_ascii_lowercase()]
                    } else {
                        vec![c]
                    }
                })
                .collect();
            let arg = cmd
                .get_arguments()
                .find(|a| a.get_long() == Some(kebab.as_str()))
                .unwrap_or_else(|| panic!("no flag --{kebab} for key {key}"));
            (key, arg.clone())
        })
        .collect()
}

/// Every file key has a flag of the same name in kebab case and an env var; and back.
#[test]
fn every_key_is_a_flag_and_an_env_var() {
    use clap::CommandFactory;
    let keys = keys_and_flags();
    for (key, arg) in &keys {
        let kebab = arg.get_long().unwrap();
        let env = arg
            .get_env()
            .unwrap_or_else(|| panic!("--{kebab} has no env var"));
        let want = if key == "gateway" {
            "LEKIWI_GATEWAY_URL".to_owned()
        } else {
            format!("LEKIWI_{}", kebab.replace('-', "_").to_ascii_uppercase())
        };
        assert_eq!(env.to_str().unwrap(), want, "env var of --{kebab}");
    }
    let flag_count = Flags::command()
        .get_arguments()
        .filter(|a| a.get_long().is_some())
        .count();
    // config and print-config (and clap's help/version, which have no long here) aside.
    assert_eq!(flag_count - 2, keys.len(), "a flag without a file key");
}

/// `ws://` to another host is refused at start unless plain text is allowed by flag, env or
/// file; loopback and `wss://` need nothing.
#[test]
fn plaintext_to_another_host_needs_the_insecure_flag() {
    let load = |args: &[&str]| {
        let mut argv = vec!["lekiwi-agent", "--config", "/nonexistent/agent.yaml"];
        argv.extend_from_slice(args);
        Config::load(&Flags::parse_from(argv), "h")
    };
    let err = load(&["--gateway", "ws://192.0.2.1:9/v1/agent"])
        .unwrap_err()
        .to_string();
    assert!(err.contains("plain ws:// to 192.0.2.1"), "{err}");
    assert!(err.contains("--insecure-allow-plaintext"), "{err}");

    for args in [
        &["--insecure-allow-plaintext"][..],
        &["--insecure-allow-plaintext=true"][..],
    ] {
        let mut argv = vec!["--gateway", "ws://192.0.2.1:9/v1/agent"];
        argv.extend_from_slice(args);
        let cfg = load(&argv).unwrap();
        assert!(cfg.insecure_allow_plaintext);
        let warning = cfg.plaintext_warning().unwrap();
        assert!(warning.starts_with("INSECURE"), "{warning}");
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("agent.yaml");
    std::fs::write(
        &path,
        "gateway: ws://gw.example.com/v1/agent\ninsecureAllowPlaintext: true\n",
    )
    .unwrap();
    let flags = Flags::parse_from(["lekiwi-agent", "--config", path.to_str().unwrap()]);
    assert!(Config::load(&flags, "h").is_ok());

    for gateway in [
        "ws://127.0.0.1:8081/v1/agent",
        "ws://localhost:8081/v1/agent",
        "ws://[::1]:8081/v1/agent",
        "wss://192.0.2.1/v1/agent",
    ] {
        let cfg = load(&["--gateway", gateway]).unwrap();
        assert_eq!(cfg.plaintext_warning(), None, "{gateway}");
    }
}
