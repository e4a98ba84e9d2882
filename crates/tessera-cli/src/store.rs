//! `tessera store check|backup|restore|accept-loss`: the operator's tools for the
//! coordinator's SQLite store (docs/store.md). The work is done by
//! [`tessera_coordinator::store::maintenance`]; this module parses, prints and sets the
//! exit status.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use tessera_coordinator::store::{maintenance, StoreUrl};

use crate::common::runtime;
use crate::coordinator::parse_store_url;

/// `tessera store ...`.
#[derive(Args, Debug)]
pub struct StoreArgs {
    #[command(subcommand)]
    command: StoreCommand,
}

#[derive(Subcommand, Debug)]
enum StoreCommand {
    /// Check a store without changing it (safe while a coordinator runs on it): the checks
    /// a coordinator's start makes (SQLite's integrity check, the schema version, the
    /// commit marker), then every row's checksum. Exit status 0 when a coordinator starts
    /// on it and every row reads back, 2 when it starts but rows are damaged (listed,
    /// with what the coordinator does about each), 1 when it refuses to start (with the
    /// start's own message).
    Check(DataArg),
    /// Write a consistent backup of a store to a new file, while a coordinator may run on
    /// it (SQLite's VACUUM INTO), then check the copy.
    Backup {
        #[command(flatten)]
        data: DataArg,
        /// The backup file to create (must not exist).
        out: PathBuf,
    },
    /// Replace a stopped coordinator's store with a checked backup. The replaced files
    /// are kept in DATA/replaced-UNIX_MS/; job ids issued after the backup are never
    /// issued again.
    Restore {
        #[command(flatten)]
        data: DataArg,
        /// The backup file (from `tessera store backup`).
        backup: PathBuf,
    },
    /// Accept a stopped coordinator's store as it is after lost commits (or start an
    /// empty one after the damaged files were moved away): the commit marker is rewritten
    /// and job ids already issued are never issued again.
    AcceptLoss(DataArg),
    /// Rebuild the indexes of a stopped coordinator's store from its tables (when the
    /// check finds only index problems), then check it.
    Reindex(DataArg),
}

#[derive(Args, Debug)]
struct DataArg {
    /// Data directory of the store (the coordinator's --data).
    #[arg(long, default_value = "tessera-data")]
    data: PathBuf,
    /// The coordinator's --store instead of --data: `sqlite:DIR`. A PostgreSQL URL is
    /// refused with what to use instead (pg_dump, pg_restore; docs/store.md).
    #[arg(long, value_name = "URL", value_parser = parse_store_url)]
    store: Option<StoreUrl>,
}

impl DataArg {
    /// Resolves `--store` into the data directory these commands work on.
    fn resolve(mut self, command: &str) -> Result<Self> {
        match self.store.take() {
            None => Ok(self),
            Some(StoreUrl::Sqlite(dir)) => Ok(Self {
                data: dir,
                store: None,
            }),
            Some(url @ StoreUrl::Postgres(_)) => bail!(
                "`tessera store {command}` works on the SQLite store only; {url} is a \
                 PostgreSQL store: {}",
                POSTGRES_TOOLS
            ),
        }
    }
}

/// What to do instead of `tessera store` on a PostgreSQL store.
const POSTGRES_TOOLS: &str = "back it up with `pg_dump --format=custom --file=FILE URL` \
     (while the coordinator runs), restore it with `pg_restore --dbname=URL FILE` into an \
     empty database (with the coordinator stopped), check it with `pg_amcheck`; \
     PostgreSQL's own WAL keeps commits, so there is no commit marker to accept a loss of \
     (docs/store.md, \"PostgreSQL\")";

/// `tessera store`.
pub fn store(args: StoreArgs) -> Result<()> {
    runtime()?.block_on(async {
        match args.command {
            StoreCommand::Check(d) => {
                let d = d.resolve("check")?;
                let report = maintenance::check(&d.data).await;
                println!("{report}");
                if !report.healthy() {
                    bail!("the store in {} is not usable", d.data.display());
                }
                if !report.clean() {
                    // Exit status 2: the coordinator starts, but rows are damaged.
                    use std::io::Write;
                    std::io::stdout().flush().ok();
                    std::process::exit(2);
                }
            }
            StoreCommand::Backup { data, out } => {
                let data = data.resolve("backup")?;
                let report = maintenance::backup(&data.data, &out)
                    .await
                    .with_context(|| format!("backing up the store in {}", data.data.display()))?;
                println!("{report}");
                if !report.healthy() {
                    bail!("the backup {} does not check", out.display());
                }
                println!("backup: {}", out.display());
            }
            StoreCommand::Restore { data, backup } => {
                let data = data.resolve("restore")?;
                let r = maintenance::restore(&data.data, &backup)
                    .await
                    .with_context(|| {
                        format!(
                            "restoring {} into {}",
                            backup.display(),
                            data.data.display()
                        )
                    })?;
                if let Some(aside) = &r.moved_to {
                    println!("replaced files moved to: {}", aside.display());
                }
                println!(
                    "restored: {} into {}",
                    backup.display(),
                    data.data.display()
                );
                println!("commit marker: {}", r.mark);
            }
            StoreCommand::AcceptLoss(d) => {
                let d = d.resolve("accept-loss")?;
                let r = maintenance::accept_loss(&d.data)
                    .await
                    .with_context(|| format!("accepting the store in {}", d.data.display()))?;
                println!("accepted: {}", d.data.display());
                println!("commit marker: {}", r.mark);
            }
            StoreCommand::Reindex(d) => {
                let d = d.resolve("reindex")?;
                let report = maintenance::reindex(&d.data)
                    .await
                    .with_context(|| format!("reindexing the store in {}", d.data.display()))?;
                println!("{report}");
                if !report.healthy() {
                    bail!("the store in {} is still not usable", d.data.display());
                }
            }
        }
        Ok(())
    })
}
