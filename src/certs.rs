//! The cluster's certificates: one certificate authority and a certificate per machine, whose
//! common name is the machine's *role* (`mwb-store`, `mwb-worker`, `mwb-client`, `mwb-query`,
//! `mwb-recorder`).
//!
//! Why one common name per role and not one per node (`sampler-0`, `sampler-1`, …): zenoh's
//! access control matches `cert_common_names` exactly (no wildcards), so per-node names would
//! have to be listed in the store's configuration, and every sampler that joins — machines that
//! come and go, §4.2 — would mean editing and restarting the store. With the role in the CN the
//! shipped `deploy/store.json5` stays as it is; each machine still gets its own key pair and
//! serial number, and its bundle name (`worker-3`) is recorded in the certificate's
//! organisational unit, so `openssl x509 -subject` says whom a certificate was issued to.
//! zenoh cannot check revocation lists: a lost key is answered by a short validity (`--days`)
//! or, at worst, a new authority.
//!
//! ```
//! use mwb::certs::{Plan, Role, generate};
//! let plan = Plan { store_hosts: vec!["10.0.0.5".into()], workers: 2, ..Plan::default() };
//! let bundle = generate(&plan)?;
//! // ca.pem + ca-key.pem, then store, worker-0, worker-1, client-0, query, recorder: three
//! // files each.
//! assert_eq!(bundle.files.len(), 2 + 6 * 3);
//! assert!(bundle.files.iter().any(|f| f.path == "worker-1/worker-key.pem" && f.secret));
//! assert_eq!(Role::Worker.common_name(), "mwb-worker");
//! # Ok::<(), mwb::certs::CertError>(())
//! ```
//!
//! Layout written by [`write_bundle`]: `ca.pem` and `ca-key.pem` at the top (the key stays with
//! the admin), then one directory per machine holding exactly what that machine installs as
//! `/etc/mwb/tls/`: `ca.pem`, `<role>.pem`, `<role>-key.pem` — the paths the configs in
//! `deploy/` name.

use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa,
    Issuer, KeyPair, KeyUsagePurpose, SanType,
};
use std::io::Write as _;
use std::net::IpAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use thiserror::Error;

/// Where the shipped configs expect a machine's bundle.
pub const INSTALL_DIR: &str = "/etc/mwb/tls/";

/// Default validity of the node certificates, in days.
pub const DEFAULT_DAYS: u32 = 365;

/// The authority outlives the certificates it signs by at least this many days.
const CA_MIN_DAYS: u32 = 3650;

/// What a certificate's holder may do on the bus: the ACL subjects in `deploy/store.json5`
/// match these common names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Store shards (the zenoh routers): serve TLS and connect to one another.
    Store,
    /// Samplers and reverse nodes: put segments, summaries, stats; take jobs.
    Worker,
    /// The CLI and the viewer: put jobs and scenes, query worlds and browsing.
    Client,
    /// A browsing coordinator run on its own (`mwb query serve`).
    Query,
    /// `mwb record` and `mwb replay`: reads everything on the bus, and a replay puts jobs,
    /// segments and summaries — as trusted as a store; keep its bundle on an admin's machine.
    Recorder,
}

impl Role {
    /// The certificate's common name, as the ACL subjects list it.
    pub fn common_name(self) -> &'static str {
        match self {
            Role::Store => "mwb-store",
            Role::Worker => "mwb-worker",
            Role::Client => "mwb-client",
            Role::Query => "mwb-query",
            Role::Recorder => "mwb-recorder",
        }
    }
    /// File stem inside a bundle: `<stem>.pem`, `<stem>-key.pem`.
    pub fn stem(self) -> &'static str {
        match self {
            Role::Store => "store",
            Role::Worker => "worker",
            Role::Client => "client",
            Role::Query => "query",
            Role::Recorder => "recorder",
        }
    }
}

/// What to issue.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Plan {
    /// Names and addresses the store is reached at (its certificate's subject alternative
    /// names; clients check the one they connect to).
    pub store_hosts: Vec<String>,
    /// Number of worker (sampler / reverse node) bundles.
    pub workers: u32,
    /// Number of client (CLI / viewer) bundles.
    pub clients: u32,
    /// Validity of the node certificates, in days.
    pub days: u32,
}

impl Default for Plan {
    fn default() -> Self {
        Self {
            store_hosts: Vec::new(),
            workers: 1,
            clients: 1,
            days: DEFAULT_DAYS,
        }
    }
}

/// One file of a bundle, relative to the output directory.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BundleFile {
    pub path: String,
    pub contents: String,
    /// A private key: written with mode 0600.
    pub secret: bool,
}

/// Everything [`generate`] made, not yet on disk.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Bundle {
    pub files: Vec<BundleFile>,
}

/// Whether [`write_bundle`] may replace files that exist.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Overwrite {
    Refuse,
    Replace,
}

#[derive(Debug, Error)]
pub enum CertError {
    #[error(
        "--store-host {host:?}: not an IP address or a DNS name ([A-Za-z0-9.-], no empty labels)"
    )]
    BadHost { host: String },
    #[error("no --store-host given: clients check the store's name, so name at least one")]
    NoStoreHost,
    #[error("--days must be at least 1")]
    NoValidity,
    #[error("issuing the {what} certificate: {source}")]
    Issue {
        what: String,
        #[source]
        source: rcgen::Error,
    },
    #[error("{}: exists (pass --force to replace it)", path.display())]
    Exists { path: PathBuf },
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// Validity window: from an hour ago (clock skew between machines) for `days` days.
#[derive(Debug, Clone, Copy)]
struct Validity {
    since_epoch: Duration,
    days: u32,
}

impl Validity {
    fn apply(self, params: &mut CertificateParams) {
        let epoch = rcgen::date_time_ymd(1970, 1, 1);
        let hour = Duration::from_secs(3600);
        params.not_before = epoch + self.since_epoch.saturating_sub(hour);
        params.not_after =
            epoch + self.since_epoch + Duration::from_secs(86_400 * u64::from(self.days));
    }
}

/// Makes the authority and every machine's bundle in memory.
pub fn generate(plan: &Plan) -> Result<Bundle, CertError> {
    if plan.store_hosts.is_empty() {
        return Err(CertError::NoStoreHost);
    }
    if plan.days == 0 {
        return Err(CertError::NoValidity);
    }
    for host in &plan.store_hosts {
        check_host(host)?;
    }
    let since_epoch = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default();
    let leaf = Validity {
        since_epoch,
        days: plan.days,
    };
    let ca_validity = Validity {
        since_epoch,
        days: plan.days.max(CA_MIN_DAYS),
    };
    let ca = Authority::new(ca_validity)?;
    let mut files = vec![
        BundleFile {
            path: "ca.pem".into(),
            contents: ca.cert_pem.clone(),
            secret: false,
        },
        BundleFile {
            path: "ca-key.pem".into(),
            contents: ca.issuer.key().serialize_pem(),
            secret: true,
        },
    ];
    let mut machines: Vec<(String, Role, &[String])> =
        vec![("store".into(), Role::Store, plan.store_hosts.as_slice())];
    machines.extend((0..plan.workers).map(|i| (format!("worker-{i}"), Role::Worker, &[][..])));
    machines.extend((0..plan.clients).map(|i| (format!("client-{i}"), Role::Client, &[][..])));
    machines.push(("query".into(), Role::Query, &[]));
    machines.push(("recorder".into(), Role::Recorder, &[]));
    for (name, role, hosts) in machines {
        let (cert, key) = ca.issue(&name, role, hosts, leaf)?;
        files.push(BundleFile {
            path: format!("{name}/ca.pem"),
            contents: ca.cert_pem.clone(),
            secret: false,
        });
        files.push(BundleFile {
            path: format!("{name}/{}.pem", role.stem()),
            contents: cert,
            secret: false,
        });
        files.push(BundleFile {
            path: format!("{name}/{}-key.pem", role.stem()),
            contents: key,
            secret: true,
        });
    }
    Ok(Bundle { files })
}

/// Writes a bundle under `dir` (created if missing). Every target is checked before anything
/// is written, so a refusal leaves the directory as it was. Keys get mode 0600.
pub fn write_bundle(
    bundle: &Bundle,
    dir: &Path,
    overwrite: Overwrite,
) -> Result<Vec<PathBuf>, CertError> {
    let targets: Vec<PathBuf> = bundle.files.iter().map(|f| dir.join(&f.path)).collect();
    if overwrite == Overwrite::Refuse
        && let Some(path) = targets.iter().find(|p| p.symlink_metadata().is_ok())
    {
        return Err(CertError::Exists { path: path.clone() });
    }
    for (file, path) in bundle.files.iter().zip(&targets) {
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|source| CertError::Io {
                path: parent.to_owned(),
                source,
            })?;
        }
        write_file(path, &file.contents, file.secret, overwrite)?;
    }
    Ok(targets)
}

fn write_file(
    path: &Path,
    contents: &str,
    secret: bool,
    overwrite: Overwrite,
) -> Result<(), CertError> {
    let io = |source| CertError::Io {
        path: path.to_owned(),
        source,
    };
    if overwrite == Overwrite::Replace {
        // Removed first, so the new file is created with the mode below even where the old
        // one had a looser one.
        match std::fs::remove_file(path) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io(e)),
        }
    }
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt as _;
        options.mode(if secret { 0o600 } else { 0o644 });
    }
    #[cfg(not(unix))]
    let _ = secret;
    let mut f = options.open(path).map_err(|e| {
        if e.kind() == std::io::ErrorKind::AlreadyExists {
            CertError::Exists {
                path: path.to_owned(),
            }
        } else {
            io(e)
        }
    })?;
    f.write_all(contents.as_bytes()).map_err(io)?;
    f.sync_all().map_err(io)
}

/// A store host must be an IP address or a DNS name (a subject alternative name either way).
fn check_host(host: &str) -> Result<(), CertError> {
    let dns = !host.is_empty()
        && host.len() <= 253
        && host.split('.').all(|label| {
            !label.is_empty()
                && label.len() <= 63
                && !label.starts_with('-')
                && label
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-')
        });
    if host.parse::<IpAddr>().is_ok() || dns {
        Ok(())
    } else {
        Err(CertError::BadHost {
            host: host.to_owned(),
        })
    }
}

/// The certificate authority: a self-signed certificate and its key.
struct Authority {
    cert_pem: String,
    issuer: Issuer<'static, KeyPair>,
}

impl Authority {
    fn new(validity: Validity) -> Result<Self, CertError> {
        let fail = |source: rcgen::Error| CertError::Issue {
            what: "authority".into(),
            source,
        };
        let mut params = CertificateParams::default();
        params.distinguished_name = DistinguishedName::new();
        params
            .distinguished_name
            .push(DnType::CommonName, "manyworlds cluster CA");
        params
            .distinguished_name
            .push(DnType::OrganizationName, "manyworlds");
        // Signs node certificates only, never another authority.
        params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
        params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        validity.apply(&mut params);
        let key = KeyPair::generate().map_err(fail)?;
        let cert = params.self_signed(&key).map_err(fail)?;
        Ok(Self {
            cert_pem: cert.pem(),
            issuer: Issuer::new(params, key),
        })
    }

    /// A node certificate: CN = the role, OU = the bundle's name, SANs = `hosts`. Every role
    /// may authenticate as a TLS client (mutual TLS); the store also as a server, and it
    /// connects to other shards as a client.
    fn issue(
        &self,
        name: &str,
        role: Role,
        hosts: &[String],
        validity: Validity,
    ) -> Result<(String, String), CertError> {
        let fail = |source: rcgen::Error| CertError::Issue {
            what: name.to_owned(),
            source,
        };
        let mut params = CertificateParams::default();
        params.subject_alt_names = hosts
            .iter()
            .map(|h| match h.parse::<IpAddr>() {
                Ok(ip) => Ok(SanType::IpAddress(ip)),
                Err(_) => h.clone().try_into().map(SanType::DnsName),
            })
            .collect::<Result<_, _>>()
            .map_err(fail)?;
        params.distinguished_name = DistinguishedName::new();
        params
            .distinguished_name
            .push(DnType::CommonName, role.common_name());
        params
            .distinguished_name
            .push(DnType::OrganizationName, "manyworlds");
        params
            .distinguished_name
            .push(DnType::OrganizationalUnitName, name);
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ClientAuth];
        if role == Role::Store {
            params
                .extended_key_usages
                .push(ExtendedKeyUsagePurpose::ServerAuth);
        }
        params.use_authority_key_identifier_extension = true;
        validity.apply(&mut params);
        let key = KeyPair::generate().map_err(fail)?;
        let cert = params.signed_by(&key, &self.issuer).map_err(fail)?;
        Ok((cert.pem(), key.serialize_pem()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan() -> Plan {
        Plan {
            store_hosts: vec!["store.lab".into(), "127.0.0.1".into()],
            workers: 2,
            clients: 1,
            days: 30,
        }
    }

    #[test]
    fn layout_names_each_machine_bundle() {
        let b = generate(&plan()).unwrap_or_else(|e| panic!("{e}"));
        let paths: Vec<&str> = b.files.iter().map(|f| f.path.as_str()).collect();
        for p in [
            "ca.pem",
            "ca-key.pem",
            "store/ca.pem",
            "store/store.pem",
            "store/store-key.pem",
            "worker-0/worker.pem",
            "worker-1/worker-key.pem",
            "client-0/client.pem",
            "query/query-key.pem",
            "recorder/recorder.pem",
            "recorder/recorder-key.pem",
        ] {
            assert!(paths.contains(&p), "{p} missing from {paths:?}");
        }
        assert!(!paths.contains(&"worker-2/worker.pem"));
        for f in &b.files {
            assert_eq!(f.secret, f.path.ends_with("-key.pem"), "{}", f.path);
            let tag = if f.secret {
                "PRIVATE KEY"
            } else {
                "CERTIFICATE"
            };
            assert!(f.contents.contains(tag), "{}", f.path);
        }
        // Each machine has its own key.
        let key = |p: &str| {
            b.files
                .iter()
                .find(|f| f.path == p)
                .map(|f| f.contents.clone())
        };
        assert_ne!(
            key("worker-0/worker-key.pem"),
            key("worker-1/worker-key.pem")
        );
    }

    #[test]
    fn bad_input_is_named() {
        let mut p = plan();
        p.store_hosts.push("bad host".into());
        let e = generate(&p)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("\"bad host\""), "{e}");
        p.store_hosts.clear();
        assert!(matches!(generate(&p), Err(CertError::NoStoreHost)));
        let mut p = plan();
        p.days = 0;
        assert!(matches!(generate(&p), Err(CertError::NoValidity)));
        for ok in ["10.1.2.3", "::1", "mwb-store", "a.b-c.d"] {
            assert!(check_host(ok).is_ok(), "{ok}");
        }
        for bad in ["", "a..b", "-a", "a_b", "x/y"] {
            assert!(check_host(bad).is_err(), "{bad:?}");
        }
    }

    #[cfg(unix)]
    #[test]
    fn writes_keys_private_and_refuses_to_overwrite() {
        use std::os::unix::fs::PermissionsExt as _;
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let b = generate(&plan()).unwrap_or_else(|e| panic!("{e}"));
        let written =
            write_bundle(&b, dir.path(), Overwrite::Refuse).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(written.len(), b.files.len());
        let mode = |p: &str| {
            std::fs::metadata(dir.path().join(p))
                .map(|m| m.permissions().mode() & 0o777)
                .unwrap_or_else(|e| panic!("{p}: {e}"))
        };
        assert_eq!(mode("ca-key.pem"), 0o600);
        assert_eq!(mode("worker-1/worker-key.pem"), 0o600);
        assert_eq!(mode("store/store.pem"), 0o644);

        // A second run names the first file in its way and changes nothing.
        let before = std::fs::read_to_string(dir.path().join("ca.pem")).unwrap_or_default();
        let again = generate(&plan()).unwrap_or_else(|e| panic!("{e}"));
        let e = write_bundle(&again, dir.path(), Overwrite::Refuse)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("ca.pem: exists"), "{e}");
        assert_eq!(
            std::fs::read_to_string(dir.path().join("ca.pem")).unwrap_or_default(),
            before
        );
        // --force replaces, keys stay 0600 even if someone loosened them.
        std::fs::set_permissions(
            dir.path().join("ca-key.pem"),
            std::fs::Permissions::from_mode(0o644),
        )
        .unwrap_or_else(|e| panic!("{e}"));
        write_bundle(&again, dir.path(), Overwrite::Replace).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(mode("ca-key.pem"), 0o600);
        assert_ne!(
            std::fs::read_to_string(dir.path().join("ca.pem")).unwrap_or_default(),
            before
        );
    }
}
