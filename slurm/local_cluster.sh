#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, on loopback, for the tests and for trying the sbatch scripts
# without a cluster (Debian/Ubuntu, as root: it installs slurmctld, slurmd, slurm-client and munge when they
# are missing).
#
#   slurm/local_cluster.sh start     # install if needed, write the config, start munged/slurmctld/slurmd,
#                                    # wait until the node is idle, print the `export SLURM_CONF=...` line
#   eval "$(slurm/local_cluster.sh env)"   # point sbatch/squeue/scontrol at it (SLURM_CONF)
#   slurm/local_cluster.sh status    # daemons, node state, queue
#   slurm/local_cluster.sh stop      # cancel its jobs, stop exactly the daemons it started (recorded pids)
#
# Everything (config, munge key and socket, state, logs, pid files) lives under $AESPLAT_SLURM_DIR
# (default /tmp/aesplat-slurm); nothing under /etc is written or read except the packages' own files.
# The node has CPUs=$(nproc) and declares 2 GPU slots without devices ($AESPLAT_SLURM_GPUS), so that
# GPU-shaped submissions are scheduled and the scripts' checks run; training there needs AESPLAT_SLURM_CPU=1
# (see slurm/train.sbatch). Ports: $AESPLAT_SLURM_PORT (slurmctld) and the next one (slurmd), default 16817.
set -euo pipefail

DIR="${AESPLAT_SLURM_DIR:-/tmp/aesplat-slurm}"
PORT="${AESPLAT_SLURM_PORT:-16817}"
GPUS="${AESPLAT_SLURM_GPUS:-2}"
NODE="$(hostname -s)"
CONF="${DIR}/slurm.conf"
MUNGE_SOCKET="${DIR}/munge/munge.socket"
MUNGE_KEY="${DIR}/munge/private/munge.key"
PACKAGES=(slurmctld slurmd slurm-client munge)

say() { echo "local_cluster: $*" >&2; }
die() { say "error: $*"; exit 1; }

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
  mkdir -p "${DIR}"/{state/ctld,state/d,log,run}
  chmod 755 "${DIR}"
  # munged wants its socket folder open to all (clients connect) and its key readable by munge alone.
  install -d -o munge -g munge -m 0755 "${DIR}/munge"
  install -d -o munge -g munge -m 0700 "${DIR}/munge/private"
  if [ ! -s "${MUNGE_KEY}" ]; then
    dd if=/dev/urandom of="${MUNGE_KEY}" bs=1024 count=1 status=none
  fi
  chown munge:munge "${MUNGE_KEY}"
  chmod 0400 "${MUNGE_KEY}"

  local cpus
  cpus="$(nproc)"
  cat >"${CONF}" <<EOF
# Written by slurm/local_cluster.sh: a one-node cluster on loopback.
ClusterName=aesplat-local
SlurmctldHost=${NODE}(127.0.0.1)
SlurmctldPort=${PORT}
SlurmdPort=$((PORT + 1))
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
# cred_expire also holds a requeued job back before it starts again (default 120 s).
AuthInfo=socket=${MUNGE_SOCKET},cred_expire=30
StateSaveLocation=${DIR}/state/ctld
SlurmdSpoolDir=${DIR}/state/d
SlurmctldPidFile=${DIR}/run/slurmctld.pid
SlurmdPidFile=${DIR}/run/slurmd.pid
SlurmctldLogFile=${DIR}/log/slurmctld.log
SlurmdLogFile=${DIR}/log/slurmd.log
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
ReturnToService=2
SchedulerParameters=sched_interval=2
NodeName=${NODE} NodeAddr=127.0.0.1 CPUs=${cpus} Gres=gpu:${GPUS} State=UNKNOWN
PartitionName=local Nodes=${NODE} Default=YES MaxTime=INFINITE State=UP
EOF
  # GPU slots backed by empty files (slurmd counts a gpu GRES by its File entries): SLURM schedules them
  # and sets SLURM_GPUS_ON_NODE; nothing is bound (task/none).
  mkdir -p "${DIR}/gpu"
  local i
  for i in $(seq 0 $((GPUS - 1))); do touch "${DIR}/gpu/slot${i}"; done
  echo "NodeName=${NODE} Name=gpu File=${DIR}/gpu/slot[0-$((GPUS - 1))]" >"${DIR}/gres.conf"
}

pid_alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

start() {
  install_packages
  if pid_alive "${DIR}/run/slurmctld.pid"; then
    say "already running (${DIR}); 'stop' first to restart"
    print_env
    return
  fi
  local port
  for port in "${PORT}" $((PORT + 1)); do
    if (exec 3<>"/dev/tcp/127.0.0.1/${port}") 2>/dev/null; then
      die "port ${port} is taken (another cluster?); stop it or set AESPLAT_SLURM_PORT"
    fi
  done
  write_config
  export SLURM_CONF="${CONF}"
  cd /  # the daemons keep the directory they start in; the job steps look it up

  runuser -u munge -- munged --socket="${MUNGE_SOCKET}" --key-file="${MUNGE_KEY}" \
    --pid-file="${DIR}/munge/munged.pid" --log-file="${DIR}/munge/private/munged.log" \
    --seed-file="${DIR}/munge/private/munged.seed" || die "munged did not start; see ${DIR}/munge/private/munged.log"
  cp "${DIR}/munge/munged.pid" "${DIR}/run/munged.pid"
  # -c: a fresh controller, no jobs recovered from an earlier cluster in this directory.
  slurmctld -c -f "${CONF}" || die "slurmctld did not start; see ${DIR}/log/slurmctld.log"
  slurmd -f "${CONF}" -N "${NODE}" || die "slurmd did not start; see ${DIR}/log/slurmd.log"
  sleep 1  # a daemon that cannot bind its port exits just after writing its pid file

  local state="" name
  for _ in $(seq 60); do
    state="$(sinfo -h -N -n "${NODE}" -o %T 2>/dev/null || true)"
    [ "${state}" = "idle" ] && break
    sleep 1
  done
  for name in munged slurmctld slurmd; do
    pid_alive "${DIR}/run/${name}.pid" || state="${state:-unreachable} (${name} exited)"
  done
  if [ "${state}" != "idle" ]; then
    tail -n 20 "${DIR}/log/slurmctld.log" "${DIR}/log/slurmd.log" >&2 || true
    stop
    die "node ${NODE} is '${state:-unreachable}', not idle, after 60 s (logs above)"
  fi
  say "node ${NODE} idle: $(nproc) CPUs, ${GPUS} GPU slots; config ${CONF}"
  print_env
}

stop() {
  export SLURM_CONF="${CONF}"
  if pid_alive "${DIR}/run/slurmctld.pid"; then
    scancel --quiet --full --partition=local 2>/dev/null || true
  fi
  local name pid
  for name in slurmd slurmctld munged; do
    pid="$(cat "${DIR}/run/${name}.pid" 2>/dev/null || true)"
    if [ -n "${pid}" ] && kill -0 "${pid}" 2>/dev/null; then
      kill "${pid}"
      for _ in $(seq 30); do kill -0 "${pid}" 2>/dev/null || break; sleep 0.5; done
      if kill -0 "${pid}" 2>/dev/null; then
        say "${name} (pid ${pid}) ignored SIGTERM for 15 s: SIGKILL"
        kill -9 "${pid}"
      fi
      say "stopped ${name} (pid ${pid})"
    fi
    rm -f "${DIR}/run/${name}.pid"
  done
}

status() {
  local name running=0
  for name in munged slurmctld slurmd; do
    if pid_alive "${DIR}/run/${name}.pid"; then
      echo "${name}: running (pid $(cat "${DIR}/run/${name}.pid"))"
      running=$((running + 1))
    else
      echo "${name}: not running"
    fi
  done
  if [ "${running}" -eq 3 ]; then
    SLURM_CONF="${CONF}" sinfo -N -o "%N %T %C %G"
    SLURM_CONF="${CONF}" squeue
    print_env
  fi
  [ "${running}" -eq 3 ]
}

print_env() { echo "export SLURM_CONF=${CONF}"; }

case "${1:-}" in
  start) start ;;
  stop) stop ;;
  status) status ;;
  env) print_env ;;
  *) echo "usage: $0 start|stop|status|env   (state in ${DIR})" >&2; exit 2 ;;
esac
