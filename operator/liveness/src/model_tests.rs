//! A model of one robot and three gateways over time (proptest; cases: `PROPTEST_CASES`):
//! random interleavings of gateways dying and restarting, Lease renewals, the robot moving
//! between gateways, disconnecting and sending heartbeats. At every step the Robot controller's
//! decision, made with the crate's real rules (the phase from [`plan`], the gateway's state
//! from its Lease, and the waits [`renewal_wait`] and [`late_write_wait`] that hold a robot of
//! an expired gateway back from `Unknown`), must agree with what the model knows:
//! - never `Online` through a gateway whose Lease expired;
//! - once the Lease of the gateway the robot's status names expired: held (nothing written)
//!   exactly while another gateway's valid Lease was last renewed before that expiry (so that
//!   gateway could still claim it), `Unknown` from then on, so at most one Lease duration later;
//! - `Online` again as soon as a live gateway holds the robot and has written it;
//! - `Offline` once the robot's disconnection was written.
//!
//! The gateways are modelled by the status they write (connected, gateway, heartbeat, the
//! write's time in the managed fields) and the Lease they renew, as `gateway.md` describes.

use std::time::Duration;

use jiff::{SignedDuration, Timestamp};
use k8s_openapi::api::coordination::v1::Lease;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::{ManagedFieldsEntry, MicroTime, Time};
use kube::runtime::reflector::{self, Store, store::Writer};
use kube::runtime::watcher;
use lekiwi_crds::contract::managers;
use lekiwi_crds::{Robot, RobotPhase, RobotSpec, RobotStatus};
use proptest::prelude::*;

use crate::gateways::{gateway_state, late_write_wait, renewal_wait, test_lease};
use crate::{Facts, plan};

/// The gateways' Leases live here (as in `test_lease`).
const NS: &str = "ops";
/// A Lease's duration (as in `test_lease`).
const LEASE: SignedDuration = SignedDuration::from_secs(15);
/// A live gateway renews its Lease every third of it.
const RENEW_EVERY: SignedDuration = SignedDuration::from_secs(5);
/// The holding gateway writes the robot's heartbeat at least this often.
const REFRESH: SignedDuration = SignedDuration::from_secs(10);
/// `--heartbeat-grace-seconds`.
const GRACE: Duration = Duration::from_secs(30);
const GATEWAYS: usize = 3;

#[derive(Clone, Debug)]
enum Op {
    /// Time passes by this many seconds (1 s steps: renewals and refreshes happen on time).
    Wait(u8),
    /// A gateway process is SIGKILLed: no more renewals or writes; its sessions are gone.
    Kill(usize),
    /// A gateway starts again and renews its Lease at once.
    Start(usize),
    /// The robot's connection (re)opens through a gateway, which writes it connected.
    Connect(usize),
    /// The robot closes its connection; its gateway writes it disconnected.
    Disconnect,
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        4 => (1u8..12).prop_map(Op::Wait),
        1 => (0..GATEWAYS).prop_map(Op::Kill),
        1 => (0..GATEWAYS).prop_map(Op::Start),
        2 => (0..GATEWAYS).prop_map(Op::Connect),
        1 => Just(Op::Disconnect),
    ]
}

/// One gateway process and its Lease.
struct Gateway {
    up: bool,
    renewed: Timestamp,
}

/// The world: the clock, the gateways, the robot's live connection and its Robot object.
struct Model {
    now: Timestamp,
    gateways: Vec<Gateway>,
    /// The gateway the robot is connected to, if that connection is alive.
    session: Option<usize>,
    robot: Robot,
    leases: Store<Lease>,
    writer: Writer<Lease>,
}

fn name(gateway: usize) -> String {
    format!("gw-{gateway}")
}

impl Model {
    fn new() -> Model {
        let (leases, writer) = reflector::store::<Lease>();
        let now: Timestamp = "2026-06-01T00:00:00Z".parse().unwrap();
        let mut model = Model {
            now,
            gateways: (0..GATEWAYS)
                .map(|_| Gateway {
                    up: true,
                    renewed: now,
                })
                .collect(),
            session: None,
            robot: Robot::new("kiwi-1", RobotSpec::default()),
            leases,
            writer,
        };
        model.robot.metadata.namespace = Some("fleet".into());
        for g in 0..GATEWAYS {
            model.renew(g);
        }
        model
    }

    fn renew(&mut self, g: usize) {
        self.gateways[g].renewed = self.now;
        let mut lease = test_lease(&name(g), 0);
        if let Some(spec) = lease.spec.as_mut() {
            spec.renew_time = Some(MicroTime(self.now));
        }
        self.writer
            .apply_watcher_event(&watcher::Event::Apply(lease));
    }

    /// Gateway `g` writes the robot's status, as its presence writer does.
    fn write(&mut self, g: usize, connected: bool) {
        let status = self.robot.status.get_or_insert_with(RobotStatus::default);
        status.connected = Some(connected);
        status.gateway = Some(name(g).into());
        if connected {
            status.last_heartbeat_time = Some(Time(self.now));
            status.connected_since.get_or_insert(Time(self.now));
        }
        self.robot.metadata.managed_fields = Some(vec![ManagedFieldsEntry {
            manager: Some(managers::GATEWAY.into()),
            operation: Some("Apply".into()),
            subresource: Some("status".into()),
            time: Some(Time(self.now)),
            ..ManagedFieldsEntry::default()
        }]);
    }

    fn apply(&mut self, op: &Op) {
        match *op {
            Op::Wait(secs) => {
                for _ in 0..secs {
                    self.now += SignedDuration::from_secs(1);
                    for g in 0..GATEWAYS {
                        let gw = &self.gateways[g];
                        if gw.up && self.now.duration_since(gw.renewed) >= RENEW_EVERY {
                            self.renew(g);
                        }
                    }
                    if let Some(g) = self.session {
                        let written = self.heartbeat().unwrap_or(self.now);
                        if self.now.duration_since(written) >= REFRESH {
                            self.write(g, true);
                        }
                    }
                }
            }
            Op::Kill(g) => {
                self.gateways[g].up = false;
                if self.session == Some(g) {
                    self.session = None;
                }
            }
            Op::Start(g) => {
                if !self.gateways[g].up {
                    self.gateways[g].up = true;
                    self.renew(g);
                }
            }
            Op::Connect(g) => {
                if self.gateways[g].up {
                    self.session = Some(g);
                    self.write(g, true);
                }
            }
            Op::Disconnect => {
                if let Some(g) = self.session.take() {
                    self.write(g, false);
                }
            }
        }
    }

    fn heartbeat(&self) -> Option<Timestamp> {
        let status = self.robot.status.as_ref()?;
        status.last_heartbeat_time.as_ref().map(|t| t.0)
    }

    /// The index of the gateway the robot's status names, and whether it says connected.
    fn shown(&self) -> Option<(usize, bool)> {
        let status = self.robot.status.as_ref()?;
        let g = status
            .gateway
            .as_deref()?
            .strip_prefix("gw-")?
            .parse()
            .ok()?;
        Some((g, status.connected == Some(true)))
    }

    /// What the Robot controller would write now: the planned phase, or `None` while a wait
    /// holds an `Unknown` back.
    fn decision(&self) -> Option<RobotPhase> {
        let status = self.robot.status.as_ref();
        let gateway = status
            .and_then(|s| s.gateway.as_deref())
            .map(|g| gateway_state(&self.leases, NS, g, self.now));
        let facts = Facts {
            now: self.now,
            heartbeat_grace: GRACE,
            gateway,
        };
        let planned = plan(&self.robot, &facts).phase;
        let held = planned == RobotPhase::Unknown
            && (renewal_wait(&self.leases, NS, &self.robot, self.now).is_some()
                || late_write_wait(&self.leases, NS, &self.robot, self.now).is_some());
        (!held).then_some(planned)
    }

    /// Whether another gateway may still claim the robot of gateway `g`, whose Lease expired at
    /// `expiry`: its Lease is still valid and was last renewed before that expiry (a renewal
    /// from after it lists every robot that moved to it). At most one Lease duration, as a
    /// gateway that stops renewing stops counting once its own Lease expires.
    fn claim_pending(&self, g: usize, expiry: Timestamp) -> bool {
        (0..GATEWAYS).filter(|&o| o != g).any(|o| {
            let renewed = self.gateways[o].renewed;
            renewed < expiry && self.now <= renewed + LEASE
        })
    }

    /// Checks the decision against what the model knows; the step's index for the message.
    fn check(&self, step: usize) -> Result<(), TestCaseError> {
        let decision = self.decision();
        let Some((g, connected)) = self.shown() else {
            prop_assert_eq!(decision, Some(RobotPhase::Pending), "step {}", step);
            return Ok(());
        };
        let expiry = self.gateways[g].renewed + LEASE;
        if decision == Some(RobotPhase::Online) {
            prop_assert!(
                self.now <= expiry,
                "step {}: Online through {} whose Lease expired at {}, now {}",
                step,
                name(g),
                expiry,
                self.now
            );
        }
        if !connected {
            prop_assert_eq!(decision, Some(RobotPhase::Offline), "step {}", step);
        } else if self.now > expiry {
            // Held while another gateway may still claim the robot, Unknown from then on.
            let expected = (!self.claim_pending(g, expiry)).then_some(RobotPhase::Unknown);
            prop_assert_eq!(
                decision,
                expected,
                "step {}: {} expired at {}, now {}",
                step,
                name(g),
                expiry,
                self.now
            );
        } else if self.session == Some(g) && self.gateways[g].up {
            prop_assert_eq!(decision, Some(RobotPhase::Online), "step {}", step);
        }
        Ok(())
    }
}

proptest! {
    #[test]
    fn the_controllers_decision_follows_the_gateways_over_any_interleaving(
        ops in proptest::collection::vec(op(), 1..80)
    ) {
        let mut model = Model::new();
        model.check(0)?;
        for (step, op) in ops.iter().enumerate() {
            model.apply(op);
            model.check(step + 1)?;
        }
    }
}

/// The cases the random walk must be able to reach are reachable: a robot whose gateway dies
/// is held until the other gateways renewed, turns `Unknown`, and is `Online` again once
/// another gateway holds it.
#[test]
fn a_dead_gateways_robot_turns_unknown_then_online_through_another() {
    let mut model = Model::new();
    model.apply(&Op::Connect(0));
    assert_eq!(model.decision(), Some(RobotPhase::Online));
    model.apply(&Op::Kill(0));
    model.apply(&Op::Wait(14));
    assert_eq!(
        model.decision(),
        Some(RobotPhase::Online),
        "the Lease is valid"
    );
    model.apply(&Op::Wait(7));
    assert_eq!(model.decision(), Some(RobotPhase::Unknown));
    model.apply(&Op::Connect(1));
    assert_eq!(model.decision(), Some(RobotPhase::Online));
    model.apply(&Op::Disconnect);
    assert_eq!(model.decision(), Some(RobotPhase::Offline));
}
