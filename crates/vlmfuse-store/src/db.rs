//! The two database engines behind the one [`crate::Store`]: SQLite (embedded, the default) and
//! PostgreSQL (a server that several replicas share, `[store] url = "postgres://..."`).
//!
//! The store's SQL is written once, in the subset both engines read alike, with `?N`
//! placeholders (rewritten to PostgreSQL's `$N` on first use and cached); parameters are borrowed
//! ([`P`]) and rows come back owned ([`Row`]). Only the schema's DDL and the engine's own
//! housekeeping (SQLite's pragmas and log checks, PostgreSQL's lease) differ. A thin layer of our
//! own rather than an ORM or `sqlx`: the store is synchronous on purpose (one writer thread owns
//! its connection and a commit is a blocking `fsync` either way), its statements are few and
//! fixed, and both client crates (`rusqlite`, `postgres`) are the engines' own well-kept
//! synchronous drivers.
//!
//! Reads page through big tables by key (`WHERE seq >= ? ORDER BY seq LIMIT n`) instead of
//! holding two cursors open on one connection, which PostgreSQL's protocol does not allow outside
//! a transaction; on SQLite a page costs one B-tree seek.

use crate::StoreError;
use std::cell::RefCell;
use std::collections::HashMap;

/// A parameter, borrowed from the caller.
#[derive(Debug, Clone, Copy)]
pub(crate) enum P<'a> {
    I(i64),
    F(f64),
    T(&'a str),
    B(&'a [u8]),
}

/// A value read back.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Val {
    Null,
    I(i64),
    F(f64),
    T(String),
    B(Vec<u8>),
}

/// A row read back, its values in the statement's column order.
#[derive(Debug, Clone)]
pub(crate) struct Row(pub(crate) Vec<Val>);

fn wrong(i: usize, want: &str, got: &Val) -> StoreError {
    let got = match got {
        Val::Null => "NULL",
        Val::I(_) => "an integer",
        Val::F(_) => "a real",
        Val::T(_) => "text",
        Val::B(_) => "a blob",
    };
    StoreError::Corrupt(format!("column {i} holds {got}, expected {want}"))
}

impl Row {
    fn at(&self, i: usize) -> Result<&Val, StoreError> {
        self.0
            .get(i)
            .ok_or_else(|| StoreError::Corrupt(format!("no column {i} in a row")))
    }
    pub(crate) fn i64(&self, i: usize) -> Result<i64, StoreError> {
        match self.at(i)? {
            Val::I(v) => Ok(*v),
            v => Err(wrong(i, "an integer", v)),
        }
    }
    pub(crate) fn u64(&self, i: usize) -> Result<u64, StoreError> {
        Ok(self.i64(i)? as u64)
    }
    pub(crate) fn opt_i64(&self, i: usize) -> Result<Option<i64>, StoreError> {
        match self.at(i)? {
            Val::Null => Ok(None),
            Val::I(v) => Ok(Some(*v)),
            v => Err(wrong(i, "an integer or NULL", v)),
        }
    }
    pub(crate) fn f64(&self, i: usize) -> Result<f64, StoreError> {
        match self.at(i)? {
            Val::F(v) => Ok(*v),
            Val::I(v) => Ok(*v as f64),
            // SQLite stores a NaN as NULL.
            Val::Null => Ok(f64::NAN),
            v => Err(wrong(i, "a real", v)),
        }
    }
    /// A boolean: SQLite's `EXISTS` gives 0/1, PostgreSQL's a `bool` (read as 0/1 too).
    pub(crate) fn bool(&self, i: usize) -> Result<bool, StoreError> {
        Ok(self.i64(i)? != 0)
    }
    pub(crate) fn str(&self, i: usize) -> Result<&str, StoreError> {
        match self.at(i)? {
            Val::T(s) => Ok(s),
            v => Err(wrong(i, "text", v)),
        }
    }
    pub(crate) fn string(&self, i: usize) -> Result<String, StoreError> {
        self.str(i).map(str::to_string)
    }
    pub(crate) fn blob(&self, i: usize) -> Result<&[u8], StoreError> {
        match self.at(i)? {
            Val::B(b) => Ok(b),
            v => Err(wrong(i, "a blob", v)),
        }
    }
}

/// Column access on a row where it lies: SQLite's borrowed from its page, PostgreSQL's as the
/// server sent it, or a [`Row`] read before. Decoding through it makes no copy of a column that
/// is not kept: a replay of a million rounds allocates only what the engine keeps, one page of
/// rows after another, instead of interleaving short-lived copies with the engine's own
/// allocations (which fragmented the heap: +85 MB RSS and slower rounds after a full replay).
pub(crate) trait Get {
    fn i64(&self, i: usize) -> Result<i64, StoreError>;
    fn opt_i64(&self, i: usize) -> Result<Option<i64>, StoreError>;
    fn str(&self, i: usize) -> Result<&str, StoreError>;
    fn blob(&self, i: usize) -> Result<&[u8], StoreError>;
    fn u64(&self, i: usize) -> Result<u64, StoreError> {
        Ok(self.i64(i)? as u64)
    }
    /// SQLite's `EXISTS` gives 0/1, PostgreSQL's a `bool`.
    fn bool(&self, i: usize) -> Result<bool, StoreError> {
        Ok(self.i64(i)? != 0)
    }
}

impl Get for Row {
    fn i64(&self, i: usize) -> Result<i64, StoreError> {
        Row::i64(self, i)
    }
    fn opt_i64(&self, i: usize) -> Result<Option<i64>, StoreError> {
        Row::opt_i64(self, i)
    }
    fn str(&self, i: usize) -> Result<&str, StoreError> {
        Row::str(self, i)
    }
    fn blob(&self, i: usize) -> Result<&[u8], StoreError> {
        Row::blob(self, i)
    }
}

fn lite_wrong(i: usize, want: &str, got: rusqlite::types::ValueRef<'_>) -> StoreError {
    StoreError::Corrupt(format!(
        "column {i} holds {:?}, expected {want}",
        got.data_type()
    ))
}

impl Get for rusqlite::Row<'_> {
    fn i64(&self, i: usize) -> Result<i64, StoreError> {
        match self.get_ref(i)? {
            rusqlite::types::ValueRef::Integer(v) => Ok(v),
            v => Err(lite_wrong(i, "an integer", v)),
        }
    }
    fn opt_i64(&self, i: usize) -> Result<Option<i64>, StoreError> {
        match self.get_ref(i)? {
            rusqlite::types::ValueRef::Null => Ok(None),
            rusqlite::types::ValueRef::Integer(v) => Ok(Some(v)),
            v => Err(lite_wrong(i, "an integer or NULL", v)),
        }
    }
    fn str(&self, i: usize) -> Result<&str, StoreError> {
        Ok(self.get_ref(i)?.as_str()?)
    }
    fn blob(&self, i: usize) -> Result<&[u8], StoreError> {
        Ok(self.get_ref(i)?.as_blob()?)
    }
}

impl Get for postgres::Row {
    fn i64(&self, i: usize) -> Result<i64, StoreError> {
        self.opt_i64(i)?
            .ok_or_else(|| StoreError::Corrupt(format!("column {i} is NULL, expected an integer")))
    }
    fn opt_i64(&self, i: usize) -> Result<Option<i64>, StoreError> {
        use postgres::types::Type;
        let t = self
            .columns()
            .get(i)
            .ok_or_else(|| StoreError::Corrupt(format!("no column {i} in a row")))?
            .type_()
            .clone();
        Ok(if t == Type::INT8 {
            self.try_get::<_, Option<i64>>(i)?
        } else if t == Type::INT4 {
            self.try_get::<_, Option<i32>>(i)?.map(i64::from)
        } else if t == Type::INT2 {
            self.try_get::<_, Option<i16>>(i)?.map(i64::from)
        } else if t == Type::BOOL {
            self.try_get::<_, Option<bool>>(i)?.map(i64::from)
        } else {
            return Err(StoreError::Corrupt(format!(
                "column {i} has type {t}, expected an integer"
            )));
        })
    }
    fn str(&self, i: usize) -> Result<&str, StoreError> {
        Ok(self.try_get::<_, &str>(i)?)
    }
    fn blob(&self, i: usize) -> Result<&[u8], StoreError> {
        Ok(self.try_get::<_, &[u8]>(i)?)
    }
}

/// `?N` placeholders as PostgreSQL writes them (`$N`); anything else unchanged. The store's
/// statements put no `?` inside string literals.
fn pg_sql(sql: &str) -> String {
    let mut out = String::with_capacity(sql.len());
    let mut chars = sql.chars().peekable();
    while let Some(c) = chars.next() {
        if c == '?' && chars.peek().is_some_and(|d| d.is_ascii_digit()) {
            out.push('$');
        } else {
            out.push(c);
        }
    }
    out
}

/// A PostgreSQL session with its prepared statements.
pub(crate) struct PgConn {
    /// `None` only while being dropped.
    client: Option<postgres::Client>,
    stmts: HashMap<&'static str, postgres::Statement>,
}

impl PgConn {
    fn client(&mut self) -> &mut postgres::Client {
        self.client.as_mut().expect("the client lives until drop")
    }
}

impl Drop for PgConn {
    /// The synchronous client closes its session by blocking on its own runtime, which panics
    /// on a thread that drives another one (a store dropped by an async task); a thread of its
    /// own does it anywhere.
    fn drop(&mut self) {
        if let Some(c) = self.client.take() {
            let _ = std::thread::Builder::new()
                .name("vlmfuse-pg-close".into())
                .spawn(move || drop(c))
                .map(|h| h.join());
        }
    }
}

/// An open database.
pub(crate) enum Db {
    Lite(rusqlite::Connection),
    /// `RefCell`: `postgres::Client` needs `&mut` for every query, the store's reads take
    /// `&self` (as rusqlite's do); a store is used by one thread at a time. Boxed: the client
    /// is large and a store is made once.
    Pg(Box<RefCell<PgConn>>),
}

impl From<postgres::Error> for StoreError {
    fn from(e: postgres::Error) -> Self {
        // The server's own message and detail, which `Display` of the client error hides
        // behind "db error".
        match e.as_db_error() {
            Some(d) => StoreError::Postgres(format!(
                "{}: {}{}",
                d.severity(),
                d.message(),
                d.detail().map(|x| format!(" ({x})")).unwrap_or_default()
            )),
            None if e.is_closed() => StoreError::Postgres(format!("the connection is closed: {e}")),
            None => StoreError::Postgres(e.to_string()),
        }
    }
}

impl rusqlite::ToSql for P<'_> {
    fn to_sql(&self) -> rusqlite::Result<rusqlite::types::ToSqlOutput<'_>> {
        use rusqlite::types::{ToSqlOutput, ValueRef};
        Ok(ToSqlOutput::Borrowed(match *self {
            P::I(v) => ValueRef::Integer(v),
            P::F(v) => ValueRef::Real(v),
            P::T(s) => ValueRef::Text(s.as_bytes()),
            P::B(b) => ValueRef::Blob(b),
        }))
    }
}

impl postgres::types::ToSql for P<'_> {
    fn to_sql(
        &self,
        ty: &postgres::types::Type,
        out: &mut bytes::BytesMut,
    ) -> Result<postgres::types::IsNull, Box<dyn std::error::Error + Sync + Send>> {
        use postgres::types::Type;
        match *self {
            // The server infers a parameter's type from its use; an `integer` column (int4)
            // gets the value narrowed, with an error rather than a wrap when it does not fit.
            P::I(v) if *ty == Type::INT4 => i32::try_from(v)?.to_sql(ty, out),
            P::I(v) => v.to_sql(ty, out),
            P::F(v) => v.to_sql(ty, out),
            P::T(s) => s.to_sql(ty, out),
            P::B(b) => b.to_sql(ty, out),
        }
    }
    fn accepts(ty: &postgres::types::Type) -> bool {
        use postgres::types::Type;
        [
            Type::INT4,
            Type::INT8,
            Type::FLOAT8,
            Type::TEXT,
            Type::VARCHAR,
            Type::BYTEA,
        ]
        .contains(ty)
    }
    postgres::types::to_sql_checked!();
}

fn lite_row(row: &rusqlite::Row<'_>) -> rusqlite::Result<Row> {
    use rusqlite::types::ValueRef;
    let n = row.as_ref().column_count();
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        out.push(match row.get_ref(i)? {
            ValueRef::Null => Val::Null,
            ValueRef::Integer(v) => Val::I(v),
            ValueRef::Real(v) => Val::F(v),
            ValueRef::Text(t) => Val::T(String::from_utf8_lossy(t).into_owned()),
            ValueRef::Blob(b) => Val::B(b.to_vec()),
        });
    }
    Ok(Row(out))
}

fn pg_row(row: &postgres::Row) -> Result<Row, StoreError> {
    use postgres::types::Type;
    let mut out = Vec::with_capacity(row.len());
    for (i, c) in row.columns().iter().enumerate() {
        let t = c.type_();
        let v = if *t == Type::INT8 {
            row.try_get::<_, Option<i64>>(i)?.map(Val::I)
        } else if *t == Type::INT4 {
            row.try_get::<_, Option<i32>>(i)?.map(|v| Val::I(v as i64))
        } else if *t == Type::INT2 {
            row.try_get::<_, Option<i16>>(i)?.map(|v| Val::I(v as i64))
        } else if *t == Type::BOOL {
            row.try_get::<_, Option<bool>>(i)?.map(|v| Val::I(v as i64))
        } else if *t == Type::FLOAT8 {
            row.try_get::<_, Option<f64>>(i)?.map(Val::F)
        } else if *t == Type::FLOAT4 {
            row.try_get::<_, Option<f32>>(i)?.map(|v| Val::F(v as f64))
        } else if *t == Type::BYTEA {
            row.try_get::<_, Option<Vec<u8>>>(i)?.map(Val::B)
        } else if *t == Type::TEXT || *t == Type::VARCHAR || *t == Type::NAME {
            row.try_get::<_, Option<String>>(i)?.map(Val::T)
        } else {
            return Err(StoreError::Corrupt(format!(
                "column {} has type {t}, which the store never writes",
                c.name()
            )));
        };
        out.push(v.unwrap_or(Val::Null));
    }
    Ok(Row(out))
}

impl Db {
    pub(crate) fn pg(client: postgres::Client) -> Self {
        Db::Pg(Box::new(RefCell::new(PgConn {
            client: Some(client),
            stmts: HashMap::new(),
        })))
    }

    pub(crate) fn is_pg(&self) -> bool {
        matches!(self, Db::Pg(_))
    }

    /// Runs `f` with the statement prepared (and cached) on the PostgreSQL session.
    fn with_pg<T>(
        c: &RefCell<PgConn>,
        sql: &'static str,
        f: impl FnOnce(&mut postgres::Client, &postgres::Statement) -> Result<T, StoreError>,
    ) -> Result<T, StoreError> {
        let mut c = c.borrow_mut();
        let c = &mut *c;
        let st = match c.stmts.get(sql) {
            Some(st) => st.clone(),
            None => {
                let st = c.client().prepare(&pg_sql(sql))?;
                c.stmts.insert(sql, st.clone());
                st
            }
        };
        f(c.client(), &st)
    }

    /// Runs a statement; the number of rows it changed.
    pub(crate) fn exec(&self, sql: &'static str, params: &[P<'_>]) -> Result<u64, StoreError> {
        match self {
            Db::Lite(c) => {
                let mut st = c.prepare_cached(sql)?;
                Ok(st.execute(rusqlite::params_from_iter(params.iter()))? as u64)
            }
            Db::Pg(c) => Self::with_pg(c, sql, |client, st| {
                let refs: Vec<&(dyn postgres::types::ToSql + Sync)> = params
                    .iter()
                    .map(|p| p as &(dyn postgres::types::ToSql + Sync))
                    .collect();
                Ok(client.execute(st, &refs)?)
            }),
        }
    }

    /// The rows of a query, all read (callers bound them with `LIMIT`).
    pub(crate) fn query(
        &self,
        sql: &'static str,
        params: &[P<'_>],
    ) -> Result<Vec<Row>, StoreError> {
        match self {
            Db::Lite(c) => {
                let mut st = c.prepare_cached(sql)?;
                let rows = st.query_map(rusqlite::params_from_iter(params.iter()), lite_row)?;
                Ok(rows.collect::<Result<_, _>>()?)
            }
            Db::Pg(c) => Self::with_pg(c, sql, |client, st| {
                let refs: Vec<&(dyn postgres::types::ToSql + Sync)> = params
                    .iter()
                    .map(|p| p as &(dyn postgres::types::ToSql + Sync))
                    .collect();
                client.query(st, &refs)?.iter().map(pg_row).collect()
            }),
        }
    }

    /// The rows of a query, each decoded in place by `f` (no copy of what `f` does not keep).
    pub(crate) fn query_with<T>(
        &self,
        sql: &'static str,
        params: &[P<'_>],
        mut f: impl FnMut(&dyn Get) -> Result<T, StoreError>,
    ) -> Result<Vec<T>, StoreError> {
        match self {
            Db::Lite(c) => {
                let mut st = c.prepare_cached(sql)?;
                let mut rows = st.query(rusqlite::params_from_iter(params.iter()))?;
                let mut out = Vec::new();
                while let Some(r) = rows.next()? {
                    out.push(f(r)?);
                }
                Ok(out)
            }
            Db::Pg(c) => Self::with_pg(c, sql, |client, st| {
                let refs: Vec<&(dyn postgres::types::ToSql + Sync)> = params
                    .iter()
                    .map(|p| p as &(dyn postgres::types::ToSql + Sync))
                    .collect();
                client
                    .query(st, &refs)?
                    .iter()
                    .map(|r| f(r as &dyn Get))
                    .collect()
            }),
        }
    }

    /// The first row of a query, if any.
    pub(crate) fn query_opt(
        &self,
        sql: &'static str,
        params: &[P<'_>],
    ) -> Result<Option<Row>, StoreError> {
        Ok(self.query(sql, params)?.into_iter().next())
    }

    /// The first row of a query, which must have one.
    pub(crate) fn query_one(&self, sql: &'static str, params: &[P<'_>]) -> Result<Row, StoreError> {
        self.query_opt(sql, params)?
            .ok_or_else(|| StoreError::Corrupt(format!("no row from {sql}")))
    }

    /// Statements without parameters, in one round trip (DDL, transaction control).
    pub(crate) fn batch(&self, sql: &str) -> Result<(), StoreError> {
        match self {
            Db::Lite(c) => Ok(c.execute_batch(sql)?),
            Db::Pg(c) => Ok(c.borrow_mut().client().batch_execute(sql)?),
        }
    }

    /// Runs `f` in one transaction: committed when it returns `Ok`, rolled back otherwise.
    /// SQLite's is `IMMEDIATE` (the write lock from the start, so that a reader beside it
    /// never turns it into a deadlock).
    pub(crate) fn tx<T>(
        &self,
        f: impl FnOnce(&Db) -> Result<T, StoreError>,
    ) -> Result<T, StoreError> {
        self.batch(if self.is_pg() {
            "BEGIN"
        } else {
            "BEGIN IMMEDIATE"
        })?;
        match f(self) {
            Ok(v) => {
                if let Err(e) = self.batch("COMMIT") {
                    let _ = self.batch("ROLLBACK");
                    return Err(e);
                }
                Ok(v)
            }
            Err(e) => {
                let _ = self.batch("ROLLBACK");
                Err(e)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placeholders_become_postgres_ones() {
        assert_eq!(
            pg_sql("SELECT a FROM t WHERE b = ?1 AND c < ?12 LIMIT ?2"),
            "SELECT a FROM t WHERE b = $1 AND c < $12 LIMIT $2"
        );
        assert_eq!(pg_sql("SELECT '?' , x ? y"), "SELECT '?' , x ? y");
    }
}
