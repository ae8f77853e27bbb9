#!/usr/bin/env bash
# A SLURM cluster of one or more nodes on this machine, on loopback, for the tests and for trying the sbatch
# scripts without a cluster (Debian/Ubuntu, as root: it installs slurmctld, slurmd, slurm-client and munge
# when they are missing).
#
#   slurm/local_cluster.sh start     # install if needed, write the config, start munged, slurmctld and a
#                                    # slurmd per node, wait until every node is idle, print the
#                                    # `export SLURM_CONF=...` line
#   eval "$(slurm/local_cluster.sh env)"   # point sbatch/squeue/scontrol at it (SLURM_CONF)
#   slurm/local_cluster.sh status    # daemons, node states, queue
#   slurm/local_cluster.sh stop      # cancel its jobs, stop exactly the daemons it started (recorded pids)
#   slurm/local_cluster.sh start-node NODE   # start one node's slurmd again (after it was stopped or lost)
#
# $AESPLAT_SLURM_NODES nodes (default 2), named <host>-1, <host>-2, ...: one slurmd each, all on this host
# (Debian's slurmd runs several per host: a NodeName each with this host as NodeHostname, a port each, %n in
# the slurmd pid, log and spool paths), each with CPUs=$(nproc). Jobs see them as separate nodes:
# `sbatch --nodes=2 --ntasks-per-node=1` puts one task on each. The node names resolve to 127.0.0.1, so a rank
# reaches another by its node's name as on a real cluster: as root, start adds the names that do not resolve
# yet to /etc/hosts, on a line tagged with this cluster's folder, and stop removes exactly that line.
#
# Everything else (config, munge key and socket, state, logs, pid files) lives under $AESPLAT_SLURM_DIR
# (default /tmp/aesplat-slurm); nothing under /etc is written or read except the packages' own files and that
# /etc/hosts line. Each node declares 2 GPU slots without devices ($AESPLAT_SLURM_GPUS), so that GPU-shaped
# submissions are scheduled and the scripts' checks run; training there needs AESPLAT_SLURM_CPU=1 (see
# slurm/train.sbatch). Ports: $AESPLAT_SLURM_PORT (slurmctld, default 16817) and the next one per node
# (slurmd).
set -euo pipefail

DIR="${AESPLAT_SLURM_DIR:-/tmp/aesplat-slurm}"
PORT="${AESPLAT_SLURM_PORT:-16817}"
GPUS="${AESPLAT_SLURM_GPUS:-2}"
NODES="${AESPLAT_SLURM_NODES:-2}"
HOST="$(hostname -s)"
CONF="${DIR}/slurm.conf"
MUNGE_SOCKET="${DIR}/munge/munge.socket"
MUNGE_KEY="${DIR}/munge/private/munge.key"
PACKAGES=(slurmctld slurmd slurm-client munge)
HOSTS_TAG="# aesplat local_cluster ${DIR}"

say() { echo "local_cluster: $*" >&2; }
die() { say "error: $*"; exit 1; }

case "${NODES}" in
  '' | *[!0-9]* | 0) die "AESPLAT_SLURM_NODES must be a whole number of nodes, 1 or more, not '${NODES}'" ;;
esac
[ -n "${DIR}" ] || die "AESPLAT_SLURM_DIR is empty"

node_names() {
  local i
  for i in $(seq "${NODES}"); do echo "${HOST}-${i}"; done
}

install_packages() {
  if command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v sbatch >/dev/null \
    && command -v munged >/dev/null; then
    return
  fi
  [ "$(id -u)" -eq 0 ] || die "SLURM is not installed; as root: apt-get install -y ${PACKAGES[*]}"
  command -v apt-get >/dev/null || die "SLURM is not installed and there is no apt-get to install ${PACKAGES[*]}"
  say "installing ${PACKAGES[*]} (apt-get)"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq "${PACKAGES[@]}" >/dev/null
}

write_config() {
  mkdir -p "${DIR}"/{state/ctld,log,run}
  chmod 755 "${DIR}"
  # munged wants its socket folder open to all (clients connect) and its key readable by munge alone.
  install -d -o munge -g munge -m 0755 "${DIR}/munge"
  install -d -o munge -g munge -m 0700 "${DIR}/munge/private"
  if [ ! -s "${MUNGE_KEY}" ]; then
    dd if=/dev/urandom of="${MUNGE_KEY}" bs=1024 count=1 status=none
  fi
  chown munge:munge "${MUNGE_KEY}"
  chmod 0400 "${MUNGE_KEY}"

  local cpus i name
  cpus="$(nproc)"
  cat >"${CONF}" <<EOF
# Written by slurm/local_cluster.sh: ${NODES} node(s) on loopback, a slurmd each, all on this host.
ClusterName=aesplat-local
SlurmctldHost=${HOST}(127.0.0.1)
SlurmctldPort=${PORT}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
# cred_expire also holds a requeued job back before it starts again (default 120 s).
AuthInfo=socket=${MUNGE_SOCKET},cred_expire=30
StateSaveLocation=${DIR}/state/ctld
SlurmdSpoolDir=${DIR}/state/d-%n
SlurmctldPidFile=${DIR}/run/slurmctld.pid
SlurmdPidFile=${DIR}/run/slurmd-%n.pid
SlurmctldLogFile=${DIR}/log/slurmctld.log
SlurmdLogFile=${DIR}/log/slurmd-%n.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
GresTypes=gpu
MpiDefault=none
SwitchType=switch/none
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
# Preemption: Lightning's SIGUSR1 handler runs "scontrol requeue"; keep finished jobs visible to
# "scontrol show job" for an hour (there is no accounting database for sacct).
JobRequeue=1
MinJobAge=3600
KillWait=10
InactiveLimit=0
# A node whose slurmd stops answering is down after SlurmdTimeout; it returns when its slurmd registers again.
SlurmdTimeout=30
ReturnToService=2
SchedulerParameters=sched_interval=2
EOF
  for i in $(seq "${NODES}"); do
    echo "NodeName=${HOST}-${i} NodeHostname=${HOST} NodeAddr=127.0.0.1 Port=$((PORT + i)) CPUs=${cpus}" \
      "Gres=gpu:${GPUS} State=UNKNOWN" >>"${CONF}"
  done
  echo "PartitionName=local Nodes=$(node_names | paste -sd, -) Default=YES MaxTime=INFINITE State=UP" >>"${CONF}"
  # GPU slots backed by empty files (slurmd counts a gpu GRES by its File entries): SLURM schedules them
  # and sets SLURM_GPUS_ON_NODE; nothing is bound (task/none).
  mkdir -p "${DIR}/gpu"
  for i in $(seq 0 $((GPUS - 1))); do touch "${DIR}/gpu/slot${i}"; done
  : >"${DIR}/gres.conf"
  for name in $(node_names); do
    echo "NodeName=${name} Name=gpu File=${DIR}/gpu/slot[0-$((GPUS - 1))]" >>"${DIR}/gres.conf"
  done
}

resolve_names() {  # every node name resolves: the missing ones go to /etc/hosts as 127.0.0.1 (as root)
  local name missing=()
  for name in $(node_names); do
    getent hosts "${name}" >/dev/null || missing+=("${name}")
  done
  [ "${#missing[@]}" -eq 0 ] && return
  [ "$(id -u)" -eq 0 ] || die "the node names ${missing[*]} do not resolve; as root, start adds them to /etc/hosts"
  echo "127.0.0.1 ${missing[*]} ${HOSTS_TAG}" >>/etc/hosts
  say "added ${missing[*]} to /etc/hosts (127.0.0.1; stop removes them)"
}

unresolve_names() {  # exactly the /etc/hosts lines start added for this cluster's folder
  grep -qF -- "${HOSTS_TAG}" /etc/hosts 2>/dev/null || return 0
  local kept
  kept="$(grep -vF -- "${HOSTS_TAG}" /etc/hosts || true)"
  printf '%s\n' "${kept}" >/etc/hosts  # in place, not renamed over: /etc/hosts may be a mount
}

pid_alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

start_node() {  # start_node NAME: that node's slurmd (its pid in run/slurmd-NAME.pid)
  local name="$1"
  pid_alive "${DIR}/run/slurmd-${name}.pid" && return
  mkdir -p "${DIR}/state/d-${name}"
  # From /: the daemons keep the directory they start in, and the job steps look it up.
  (cd / && SLURM_CONF="${CONF}" slurmd -f "${CONF}" -N "${name}") \
    || die "slurmd of ${name} did not start; see ${DIR}/log/slurmd-${name}.log"
}

wait_idle() {  # wait_idle NAME...: 0 once every node named is idle; else 1 after 60 s, the states printed
  local name state states=""
  for _ in $(seq 60); do
    states=""
    for name in "$@"; do
      state="$(SLURM_CONF="${CONF}" sinfo -h -N -n "${name}" -o %T 2>/dev/null | head -n 1 || true)"
      [ "${state}" = "idle" ] || states="${states} ${name}=${state:-unreachable}"
    done
    [ -z "${states}" ] && return 0
    sleep 1
  done
  echo "${states# }"
  return 1
}

start() {
  install_packages
  if pid_alive "${DIR}/run/slurmctld.pid"; then
    say "already running (${DIR}); 'stop' first to restart"
    print_env
    return
  fi
  local port name
  for port in $(seq "${PORT}" $((PORT + NODES))); do
    if (exec 3<>"/dev/tcp/127.0.0.1/${port}") 2>/dev/null; then
      die "port ${port} is taken (another cluster?); stop it or set AESPLAT_SLURM_PORT"
    fi
  done
  write_config
  resolve_names
  export SLURM_CONF="${CONF}"
  cd /  # the daemons keep the directory they start in; the job steps look it up

  runuser -u munge -- munged --socket="${MUNGE_SOCKET}" --key-file="${MUNGE_KEY}" \
    --pid-file="${DIR}/munge/munged.pid" --log-file="${DIR}/munge/private/munged.log" \
    --seed-file="${DIR}/munge/private/munged.seed" || die "munged did not start; see ${DIR}/munge/private/munged.log"
  cp "${DIR}/munge/munged.pid" "${DIR}/run/munged.pid"
  # -c: a fresh controller, no jobs recovered from an earlier cluster in this directory.
  slurmctld -c -f "${CONF}" || die "slurmctld did not start; see ${DIR}/log/slurmctld.log"
  for name in $(node_names); do start_node "${name}"; done
  sleep 1  # a daemon that cannot bind its port exits just after writing its pid file

  local states
  states="$(wait_idle $(node_names))" || true
  pid_alive "${DIR}/run/munged.pid" || states="${states} (munged exited)"
  pid_alive "${DIR}/run/slurmctld.pid" || states="${states} (slurmctld exited)"
  for name in $(node_names); do
    pid_alive "${DIR}/run/slurmd-${name}.pid" || states="${states} (slurmd of ${name} exited)"
  done
  if [ -n "${states}" ]; then
    tail -n 20 "${DIR}"/log/*.log >&2 || true
    stop
    die "not every node is idle after 60 s: ${states# } (logs above)"
  fi
  say "${NODES} node(s) idle ($(node_names | paste -sd' ' -)): $(nproc) CPUs and ${GPUS} GPU slots each;" \
    "config ${CONF}"
  print_env
}

stop_pid() {  # stop_pid NAME PIDFILE: TERM, then KILL after 15 s, then forget the pid file
  local pid
  pid="$(cat "$2" 2>/dev/null || true)"
  if [ -n "${pid}" ] && kill -0 "${pid}" 2>/dev/null; then
    kill "${pid}"
    for _ in $(seq 30); do kill -0 "${pid}" 2>/dev/null || break; sleep 0.5; done
    if kill -0 "${pid}" 2>/dev/null; then
      say "$1 (pid ${pid}) ignored SIGTERM for 15 s: SIGKILL"
      kill -9 "${pid}"
    fi
    say "stopped $1 (pid ${pid})"
  fi
  rm -f "$2"
}

stop() {
  export SLURM_CONF="${CONF}"
  if pid_alive "${DIR}/run/slurmctld.pid"; then
    scancel --quiet --full --partition=local 2>/dev/null || true
  fi
  local file
  for file in "${DIR}"/run/slurmd-*.pid; do
    [ -e "${file}" ] || continue
    file="${file##*/}"
    stop_pid "${file%.pid}" "${DIR}/run/${file}"
  done
  stop_pid slurmctld "${DIR}/run/slurmctld.pid"
  stop_pid munged "${DIR}/run/munged.pid"
  unresolve_names
}

status() {
  local name missing=0
  for name in munged slurmctld $(node_names | sed 's/^/slurmd-/'); do
    if pid_alive "${DIR}/run/${name}.pid"; then
      echo "${name}: running (pid $(cat "${DIR}/run/${name}.pid"))"
    else
      echo "${name}: not running"
      missing=$((missing + 1))
    fi
  done
  if pid_alive "${DIR}/run/slurmctld.pid"; then
    SLURM_CONF="${CONF}" sinfo -N -o "%N %T %C %G"
    SLURM_CONF="${CONF}" squeue
    print_env
  fi
  [ "${missing}" -eq 0 ]
}

print_env() { echo "export SLURM_CONF=${CONF}"; }

case "${1:-}" in
  start) start ;;
  stop) stop ;;
  status) status ;;
  env) print_env ;;
  start-node)
    [ -n "${2:-}" ] && node_names | grep -qx -- "$2" || die "start-node NODE: one of $(node_names | paste -sd' ' -)"
    pid_alive "${DIR}/run/slurmctld.pid" || die "the cluster in ${DIR} is not running; 'start' it"
    start_node "$2"
    wait_idle "$2" >/dev/null || die "node $2 is not idle 60 s after its slurmd started"
    say "node $2 idle"
    ;;
  *) echo "usage: $0 start|stop|status|env|start-node NODE   (state in ${DIR})" >&2; exit 2 ;;
esac
